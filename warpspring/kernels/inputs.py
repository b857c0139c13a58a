"""Live inputs: the values a user may change between frames, in one small device table read by the kernels.

A captured graph replays its kernels with the arguments it was captured with, so a value passed by value
(or compiled in) would be frozen into it. Gravity, drag and the stabiliser thresholds therefore live in
one table, ``inputs`` of shape [rows, INPUT_COUNT] in the model's precision, that every kernel reads;
a host write to it (or a keyframe track evaluated on the device, ``tracks.py``) is seen by the next
replay. Only whether a term exists at all (gravity on, a clamp on) specialises a kernel.

Columns are the ``INPUT_*`` slots below (a vector input takes consecutive columns); rows are worlds: world
w reads row w (a model of one world has one row).
"""

import functools

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

INPUT_GRAVITY = 0  # gravitational acceleration [m/s²], three columns (x, y, z)
INPUT_DRAG = 3  # viscous drag coefficient [N·s/m]: f = -drag · v on every particle
INPUT_MAX_SPRING_FORCE = 4  # clamp of a spring's force magnitude [N]
INPUT_MAX_PARTICLE_FORCE = 5  # clamp of a particle's total force magnitude [N]
INPUT_MAX_SPEED = 6  # clamp of a particle's speed [m/s]
INPUT_MAX_STRAIN = 7  # strain limit of Provot's strain limiting [-]
INPUT_BIPHASIC_STRAIN = 8  # strain beyond which biphasic springs stiffen [-]
INPUT_BIPHASIC_RATIO = 9  # stiffness beyond that strain over stiffness below it [-]
INPUT_WIND = 10  # the wind's velocity [m/s], three columns (x, y, z): the air moving past cloth triangles
INPUT_AIR_DENSITY = 13  # the air's density [kg/m³] in the aerodynamic forces
INPUT_WIND_NOISE = 14  # relative amplitude [-] of the wind's spatial noise: w · (1 + a · noise(x))
INPUT_COUNT = 15

#: Name, first column and width of every input (the names the API, scene files and tracks use).
INPUTS = {
    "gravity": (INPUT_GRAVITY, 3),
    "drag": (INPUT_DRAG, 1),
    "max_spring_force": (INPUT_MAX_SPRING_FORCE, 1),
    "max_particle_force": (INPUT_MAX_PARTICLE_FORCE, 1),
    "max_speed": (INPUT_MAX_SPEED, 1),
    "max_strain": (INPUT_MAX_STRAIN, 1),
    "biphasic_strain": (INPUT_BIPHASIC_STRAIN, 1),
    "biphasic_ratio": (INPUT_BIPHASIC_RATIO, 1),
    "wind": (INPUT_WIND, 3),
    "air_density": (INPUT_AIR_DENSITY, 1),
    "wind_noise": (INPUT_WIND_NOISE, 1),
}


@functools.cache
def input_funcs(scalar: type):
    """``input_vec3(inputs, world, slot)``: three consecutive columns of a world's row as a vector."""
    vec3 = vec3_type(scalar)

    @wp.func
    def input_vec3(inputs: wp.array2d[scalar], world: int, slot: int) -> vec3:
        return vec3(inputs[world, slot], inputs[world, slot + 1], inputs[world, slot + 2])

    return input_vec3
