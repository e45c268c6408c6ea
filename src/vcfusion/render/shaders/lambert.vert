#version 330 core
// Flat-coloured, Lambert-lit meshes for the ego camera (replaces pyrender's PBR mesh shader,
// which costs about 4x more per fragment under llvmpipe). Attribute locations follow
// pyrender's: 0 position, NORMAL_LOC, COLOR_0_LOC, INST_M_LOC (instancing matrix).
layout(location = 0) in vec3 position;
layout(location = NORMAL_LOC) in vec3 normal;
#ifdef COLOR_0_LOC
layout(location = COLOR_0_LOC) in vec4 color_0;
#endif
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

out vec3 world_position;
out vec3 world_normal;
out vec3 vertex_colour;

void main()
{
    mat4 model = M * inst_m;
    vec4 world = model * vec4(position, 1.0);
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
