#version 330 core
// Ambient + one directional light (Lambert), distance haze towards the sky colour.
// The output ALPHA carries the instance code of the drawn object: material.base_color_factor.a
// = code / 255 (0 for the static scene and the cleared sky), written unblended, so the colour
// pass yields the instance map too (see vcfusion.vision.render).
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

out vec4 frag_color;

// Must equal vcfusion.vision.meshes.SKY (checked by a test).
const vec3 SKY = vec3(0.62, 0.76, 0.92);
const float HAZE_M = 1400.0;

void main()
{
    vec3 n = normalize(world_normal);
    float sun = max(dot(n, -directional_lights[0].direction), 0.0);
    vec3 light = ambient_light + directional_lights[0].color * directional_lights[0].intensity * sun;
    vec3 albedo = vertex_colour * material.base_color_factor.rgb;
    vec3 lit = albedo * light;
    float haze = 1.0 - exp(-length(world_position - cam_pos) / HAZE_M);
    frag_color = vec4(mix(lit, SKY, haze), material.base_color_factor.a);
}
