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

float hash(vec2 p)  // in [0, 1); multiplications only (a sine costs a polynomial under llvmpipe)
{
    vec3 p3 = fract(vec3(p.xyx) * 0.1031);
    p3 += dot(p3, p3.yzx + 33.33);
    return fract((p3.x + p3.y) * p3.z);
}

float value_noise(vec2 p)
{
    vec2 i = floor(p);
    vec2 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash(i), hash(i + vec2(1.0, 0.0)), f.x), mix(hash(i + vec2(0.0, 1.0)), hash(i + vec2(1.0, 1.0)), f.x), f.y);
}

// llvmpipe (OSMesa) evaluates both sides of a branch that differs between neighbouring
// fragments (and, measured, an `if` that no fragment takes still costs), so every material runs
// one path with per-material weights picked by cheap selects, and the program is compiled twice:
// for vehicles (pyrender defines TEXCOORD_1_LOC: their primitives carry a second texture
// coordinate as the flag) with reflections and highlights, for the static scene with the
// asphalt and grass patches.
void main()
{
    vec3 n = normalize(world_normal);
    vec3 to_cam = cam_pos - world_position;
    float dist = length(to_cam);
    vec3 v = to_cam / dist;
    vec3 l = -directional_lights[0].direction;
    vec3 sun = directional_lights[0].color * directional_lights[0].intensity;
    bool shadow = mat_id == MAT_SHADOW;
    bool ground = mat_id == MAT_ASPHALT || mat_id == MAT_PAINT_MARK || shadow;
    bool grass = mat_id == MAT_GRASS;
    bool foliage = mat_id == MAT_FOLIAGE;
    vec2 p = world_position.xy;
    // Grain: asphalt chippings near the camera (faded where they would only flicker), leaf clumps.
    float grain = hash(floor(foliage ? p * 3.0 + world_position.z * 2.0 : p * 30.0)) - 0.5;
    float grain_w = ground ? 0.16 * clamp(1.0 - dist / 25.0, 0.0, 1.0) : (foliage ? 0.4 : 0.0);
    // Patches: older and newer asphalt stretched along the road, meadows of lighter and darker grass.
#ifdef TEXCOORD_1_LOC
    float patches = 0.0;
#else
    float patches = value_noise(grass ? p * 0.05 : p * vec2(0.08, 0.3)) - 0.5;
#endif
    float patch_w = ground ? 0.16 : (grass ? 0.35 : 0.0);
    // The shadow is the asphalt under it in ambient light only.
    vec3 albedo = shadow ? vec3(72.0, 74.0, 78.0) / 255.0 : vertex_colour;
    albedo *= 1.0 + grain * grain_w + patches * patch_w;
    float ndl = shadow ? 0.0 : max(dot(n, l), 0.0);
    vec3 diffuse = albedo * (ambient_light * (shadow ? 0.85 : 1.0) + sun * ndl);
    vec3 colour = mat_id == MAT_LAMP ? vertex_colour * (0.75 + 0.35 * ndl) : diffuse;

#ifdef TEXCOORD_1_LOC
    // Paint, glass and metal: Fresnel-weighted sky reflection and a Blinn-Phong highlight.
    bool paint = mat_id == MAT_PAINT;
    bool glass = mat_id == MAT_GLASS;
    bool metal = mat_id == MAT_METAL;
    if (paint || glass || metal) {
        vec3 ns = dot(n, v) < 0.0 ? -n : n;
        float nv = max(dot(ns, v), 0.0);
        float f5 = (1.0 - nv) * (1.0 - nv);
        f5 = f5 * f5 * (1.0 - nv);
        vec3 env = sky(reflect(-v, ns).z);
        float nh = max(dot(ns, normalize(l + v)), 0.0);
        float shininess = glass ? 200.0 : (paint ? 80.0 : 20.0);
        float highlight = pow(nh, shininess) * (glass ? 1.2 : (paint ? 0.45 : 0.3));
        float f = glass ? 0.12 + 0.75 * f5 : (paint ? 0.06 + 0.6 * f5 : 0.35);
        vec3 base = glass ? albedo * 0.6 : (metal ? diffuse : diffuse);
        env = metal ? env * albedo * 1.3 : env;
        colour = mix(base, env, f) + sun * highlight * (glass ? 1.0 : ndl);
    }
#endif
    float haze = 1.0 - exp(-dist / HAZE_M);
    float code = shadow ? 0.0 : material.base_color_factor.a;
    frag_color = vec4(mix(colour, HORIZON, haze), code);
}
