#version 330 core
// The ego camera's vertex shader (replaces pyrender's mesh.vert). Attribute locations follow
// pyrender's: 0 position, NORMAL_LOC, COLOR_0_LOC, TEXCOORD_0_LOC (x = material id, see
// vcfusion.render.materials), INST_M_LOC (instancing matrix).
// A vehicle's contact shadow (MAT_SHADOW) is a footprint box flattened here along the sun onto
// the plane SHADOW_Z above the vehicle's own ground: a planar projected shadow, any heading.
layout(location = 0) in vec3 position;
layout(location = NORMAL_LOC) in vec3 normal;
#ifdef COLOR_0_LOC
layout(location = COLOR_0_LOC) in vec4 color_0;
#endif
#ifdef TEXCOORD_0_LOC
layout(location = TEXCOORD_0_LOC) in vec2 texcoord_0;
#endif
layout(location = INST_M_LOC) in mat4 inst_m;

struct DirectionalLight {
    vec3 direction;
    vec3 color;
    float intensity;
};

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;
uniform DirectionalLight directional_lights[1];

out vec3 world_position;
out vec3 world_normal;
out vec3 vertex_colour;
flat out int mat_id;

const int MAT_SHADOW = 4;
const float SHADOW_Z = 0.03;  // vcfusion.render.vehicles.SHADOW_Z

void main()
{
    mat4 model = M * inst_m;
    vec4 world = model * vec4(position, 1.0);
#ifdef TEXCOORD_0_LOC
    mat_id = int(texcoord_0.x + 0.5);
#else
    mat_id = 0;
#endif
    if (mat_id == MAT_SHADOW) {
        vec3 d = directional_lights[0].direction;  // the light travels along d (d.z < 0)
        float ground = (model * vec4(0.0, 0.0, 0.0, 1.0)).z + SHADOW_Z;
        world.xyz -= d * ((world.z - ground) / min(d.z, -0.05));
    }
    gl_Position = P * V * world;
    world_position = world.xyz;
    // Models are placed by rigid motions only, so the rotation part transforms normals.
    world_normal = mat3(model) * normal;
#ifdef COLOR_0_LOC
    vertex_colour = color_0.rgb;
#else
    vertex_colour = vec3(1.0);
#endif
}
