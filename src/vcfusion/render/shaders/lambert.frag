#version 330 core
// The ego camera's fragment shader: ambient + sun (Lambert), Blinn-Phong highlights and a
// Fresnel reflection of the sky on paint, glass and metal, procedural asphalt and grass, the
// contact shadows, distance haze towards the horizon colour.
// The output ALPHA carries the instance code of the drawn object: material.base_color_factor.a
// = code / 255 (0 for the static scene and the cleared sky), written unblended, so the colour
// pass yields the instance map too (see vcfusion.render.renderer). Shadows write 0: they are
// ground, not vehicle.
struct Material {
    vec4 base_color_factor;
};
struct DirectionalLight {
    vec3 direction;
    vec3 color;
    float intensity;
};

uniform Material material;
uniform DirectionalLight directional_lights[1];
uniform vec3 ambient_light;
uniform vec3 cam_pos;

in vec3 world_position;
in vec3 world_normal;
in vec3 vertex_colour;
flat in int mat_id;

out vec4 frag_color;

// Material ids: vcfusion.render.materials (checked by a test).
const int MAT_MATTE = 0;
const int MAT_PAINT = 1;
const int MAT_GLASS = 2;
const int MAT_LAMP = 3;
const int MAT_SHADOW = 4;
const int MAT_METAL = 5;
const int MAT_ASPHALT = 6;
const int MAT_PAINT_MARK = 7;
const int MAT_GRASS = 8;
const int MAT_FOLIAGE = 9;

// Sky colours: SKY must equal vcfusion.render.meshes.SKY, HORIZON and ZENITH
// vcfusion.render.sky (checked by a test); sky() is the same gradient as the background.
const vec3 SKY = vec3(0.62, 0.76, 0.92);
const vec3 HORIZON = vec3(0.8, 0.85, 0.9);
const vec3 ZENITH = vec3(0.38, 0.55, 0.84);
const vec3 GROUND_SEEN = vec3(0.25, 0.26, 0.25);  // what paint and glass reflect below the horizon
const float HAZE_M = 900.0;

vec3 sky(float s)  // s = sine of the elevation of a view direction
{
    if (s < 0.0) return mix(HORIZON * 0.55, GROUND_SEEN, clamp(-s * 6.0, 0.0, 1.0));
    vec3 c = mix(HORIZON, SKY, smoothstep(0.0, 0.4, s));
    return mix(c, ZENITH, smoothstep(0.4, 1.0, s));
}

float hash(vec2 p)
{
    return fract(sin(dot(p, vec2(12.9898, 78.233))) * 43758.5453);
}

float value_noise(vec2 p)
{
    vec2 i = floor(p);
    vec2 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash(i), hash(i + vec2(1.0, 0.0)), f.x), mix(hash(i + vec2(0.0, 1.0)), hash(i + vec2(1.0, 1.0)), f.x), f.y);
}

// Asphalt albedo factor at a ground point: grain (fading with distance, where it would only
// flicker), patches of older and newer surface.
float asphalt(vec2 p, float dist)
{
    float grain = (hash(floor(p * 30.0)) - 0.5) * 0.16 * clamp(1.0 - dist / 25.0, 0.0, 1.0);
    float patches = (value_noise(p * vec2(0.08, 0.3)) - 0.5) * 0.16;
    return 1.0 + grain + patches;
}

void main()
{
    vec3 n = normalize(world_normal);
    vec3 to_cam = cam_pos - world_position;
    float dist = length(to_cam);
    vec3 v = to_cam / dist;
    vec3 l = -directional_lights[0].direction;
    vec3 sun = directional_lights[0].color * directional_lights[0].intensity;
    float ndl = max(dot(n, l), 0.0);
    vec3 albedo = vertex_colour;
    float code = material.base_color_factor.a;
    vec3 colour;
    if (mat_id == MAT_SHADOW) {
        // The shadowed asphalt: its albedo in ambient light only.
        albedo = vec3(72.0, 74.0, 78.0) / 255.0 * asphalt(world_position.xy, dist);
        colour = albedo * ambient_light * 0.85;
        code = 0.0;
    } else if (mat_id == MAT_LAMP) {
        colour = albedo * (0.75 + 0.35 * ndl);
    } else {
        if (mat_id == MAT_ASPHALT || mat_id == MAT_PAINT_MARK) {
            albedo *= asphalt(world_position.xy, dist);
        } else if (mat_id == MAT_GRASS) {
            albedo *= 0.85 + 0.3 * value_noise(world_position.xy * 0.05) + 0.1 * value_noise(world_position.xy * 0.7);
        } else if (mat_id == MAT_FOLIAGE) {
            albedo *= 0.8 + 0.4 * hash(floor(world_position.xy * 3.0 + world_position.z * 2.0));
        }
        colour = albedo * (ambient_light + sun * ndl);
        if (mat_id == MAT_PAINT || mat_id == MAT_GLASS || mat_id == MAT_METAL) {
            if (dot(n, v) < 0.0) n = -n;
            vec3 h = normalize(l + v);
            float nh = max(dot(n, h), 0.0);
            float fresnel = pow(1.0 - max(dot(n, v), 0.0), 5.0);
            vec3 r = reflect(-v, n);
            vec3 env = sky(r.z);
            if (mat_id == MAT_PAINT) {
                float f = 0.06 + 0.6 * fresnel;
                colour = mix(colour, env, f) + sun * (0.45 * pow(nh, 80.0) + 0.08 * pow(nh, 8.0)) * ndl;
            } else if (mat_id == MAT_GLASS) {
                float f = 0.12 + 0.75 * fresnel;
                colour = mix(albedo * 0.6, env, f) + sun * 1.2 * pow(nh, 200.0);
            } else {
                colour = mix(colour, env * albedo * 1.3, 0.35) + sun * 0.3 * pow(nh, 20.0);
            }
        }
    }
    float haze = 1.0 - exp(-dist / HAZE_M);
    frag_color = vec4(mix(colour, HORIZON, haze), code);
}
