"""Keyframe tracks evaluated on the device: the value and the rate of change of an input at any time.

All tracks of a model share one table (:class:`Tracks`, float64 throughout, so a track's time stays
exact over long runs): track k owns the keys ``key_start[k] .. key_start[k + 1] - 1``, at increasing
times, each with a value (up to three components; scalars use the first) and, for smooth interpolation,
the derivative at the key. Between two keys a track is

* step: the earlier key's value (right-continuous: at a key time, that key's value); rate 0;
* linear: the straight line between the keys; rate (v₁ - v₀)/(t₁ - t₀);
* smooth: the cubic Hermite curve through both keys with the keys' derivatives (C¹; the host chooses
  monotone derivatives, Fritsch-Carlson / PCHIP, so the curve never overshoots its keys).

Before the first key a track holds its first value and after the last its last (rate 0), or with cyclic
extrapolation repeats itself with the period t_last - t_first.

``apply_input_tracks_kernel`` writes the animated live inputs (``inputs.py``) at a state's time, one
thread per animated input of each world (a world's row of the input table, at the world's time); kinematic pins (``kinematics.py``) sample their tracks themselves.
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})

TRACK_STEP, TRACK_LINEAR, TRACK_SMOOTH = 0, 1, 2
EXTRAPOLATE_HOLD, EXTRAPOLATE_CYCLE = 0, 1


@wp.struct
class Tracks:
    """Every track of a model, as one table of keys (see the module docstring)."""

    key_start: wp.array[wp.int32]  # [track_count + 1], first key of each track; the last entry is key_count
    time: wp.array[wp.float64]  # [s], shape [key_count], increasing within a track
    value: wp.array[wp.vec3d]  # shape [key_count], the value at each key (a scalar in component 0)
    tangent: wp.array[wp.vec3d]  # [value/s], shape [key_count], the derivative at each key (smooth only)
    interpolation: wp.array[wp.int32]  # shape [track_count], TRACK_*
    extrapolation: wp.array[wp.int32]  # shape [track_count], EXTRAPOLATE_*


@wp.func
def track_sample(tracks: Tracks, track: int, t: wp.float64):
    """The value of ``track`` at time ``t`` [s] and its rate of change [value/s]."""
    first = tracks.key_start[track]
    last = tracks.key_start[track + 1] - 1
    t_first = tracks.time[first]
    t_last = tracks.time[last]
    zero = wp.vec3d(wp.float64(0.0))
    if tracks.extrapolation[track] == EXTRAPOLATE_CYCLE and t_last > t_first:
        period = t_last - t_first
        t = t - wp.floor((t - t_first) / period) * period
    if t < t_first or last == first:
        return tracks.value[first], zero
    if t > t_last:
        return tracks.value[last], zero
    # The segment [a, a + 1] holding t: the last key at or before t, but never the last key itself.
    a = first
    b = last
    while b - a > 1:
        middle = (a + b) // 2
        if tracks.time[middle] <= t:
            a = middle
        else:
            b = middle
    b = a + 1
    va = tracks.value[a]
    vb = tracks.value[b]
    mode = tracks.interpolation[track]
    if mode == TRACK_STEP:
        if t >= tracks.time[b]:
            return vb, zero
        return va, zero
    h = tracks.time[b] - tracks.time[a]
    s = (t - tracks.time[a]) / h
    if mode == TRACK_LINEAR:
        return va + s * (vb - va), (vb - va) / h
    # Cubic Hermite basis on s ∈ [0, 1] and its derivative d/ds.
    s2 = s * s
    s3 = s2 * s
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    three = wp.float64(3.0)
    h00 = two * s3 - three * s2 + one
    h10 = s3 - two * s2 + s
    h01 = three * s2 - two * s3
    h11 = s3 - s2
    d00 = wp.float64(6.0) * (s2 - s)
    d10 = three * s2 - wp.float64(4.0) * s + one
    d01 = -d00
    d11 = three * s2 - two * s
    ma = tracks.tangent[a] * h
    mb = tracks.tangent[b] * h
    value = h00 * va + h10 * ma + h01 * vb + h11 * mb
    rate = (d00 * va + d10 * ma + d01 * vb + d11 * mb) / h
    return value, rate


@wp.kernel(enable_backward=False)
def sample_tracks(
    # In:
    tracks: Tracks,
    track: wp.array[wp.int32],
    time: wp.array[wp.float64],
    # Out:
    value_out: wp.array[wp.vec3d],
    rate_out: wp.array[wp.vec3d],
):
    """Sample ``track[k]`` at ``time[k]`` (for inspection and tests)."""
    k = wp.tid()
    v, r = track_sample(tracks, track[k], time[k])
    value_out[k] = v
    rate_out[k] = r


@wp.struct
class WorldInputs:
    """The animated inputs by world, for a kernel that writes a world's own (``frames.py``): entry
    ``order[a]`` for a in ``start[w] .. start[w + 1] - 1`` is one of world w's, with the columns of
    ``apply_input_tracks_kernel``."""

    track: wp.array[wp.int32]  # each entry's track, shape [count]
    slot: wp.array[wp.int32]  # its first input-table column, shape [count]
    width: wp.array[wp.int32]  # its components (1 or 3), shape [count]
    order: wp.array[wp.int32]  # the entries sorted by world, shape [count]
    start: wp.array[wp.int32]  # each world's first position in ``order``, shape [world_count + 1]


@functools.cache
def input_write_func(scalar: type):
    """``write_input(tracks, track, t, world, slot, width, inputs_out)``: ``track``'s value at ``t`` [s], its first
    ``width`` components, into world ``world``'s columns ``slot...`` of the input table (one animated input)."""

    @wp.func
    def write_input(tracks: Tracks, track: int, t: wp.float64, world: int, slot: int, width: int,
                    inputs_out: wp.array2d[scalar]):
        value, rate = track_sample(tracks, track, t)
        for c in range(width):
            inputs_out[world, slot + c] = scalar(value[c])

    return write_input


@functools.cache
def world_inputs_func(scalar: type):
    """``write_world_inputs(world, first, stride, tracks, animated, t, inputs_out)``: world ``world``'s animated
    inputs at its time ``t`` [s] written into its row of the input table, entries ``first``, ``first + stride``,
    ... of its own (``input_write_func``, as ``apply_input_tracks_kernel`` writes them)."""
    write_input = input_write_func(scalar)

    @wp.func
    def write_world_inputs(world: int, first: int, stride: int, tracks: Tracks, animated: WorldInputs,
                           t: wp.float64, inputs_out: wp.array2d[scalar]):
        a = animated.start[world] + first
        while a < animated.start[world + 1]:
            e = animated.order[a]
            write_input(tracks, animated.track[e], t, world, animated.slot[e], animated.width[e], inputs_out)
            a += stride

    return write_world_inputs


@functools.cache
def apply_input_tracks_kernel(scalar: type):
    """Kernel writing every animated input at the time of a state: thread a evaluates track
    ``input_track[a]`` at the time of world ``input_world[a]`` and writes its first ``input_width[a]``
    components to that world's columns ``input_slot[a]...`` of the input table."""
    write_input = input_write_func(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def apply_input_tracks(
        # Model:
        tracks: Tracks,
        input_track: wp.array[wp.int32],
        input_world: wp.array[wp.int32],
        input_slot: wp.array[wp.int32],
        input_width: wp.array[wp.int32],
        # State in:
        time: wp.array[wp.float64],
        # Out:
        inputs_out: wp.array2d[scalar],
    ):
        a = wp.tid()
        world = input_world[a]
        write_input(tracks, input_track[a], time[world], world, input_slot[a], input_width[a], inputs_out)

    return apply_input_tracks
