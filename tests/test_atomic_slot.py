"""``kernels/linalg``'s warp-level helpers. ``atomic_slot``: a slot of a list claimed through its counter,
warp-aggregated on CUDA. Every claim gets its own slot, the slots of a counter are exactly 0 … claims − 1, and the
counter ends at the claims, also where only some lanes of a warp claim and neighbouring lanes claim from different
counters. ``atomic_raise``: each entry ends at the largest value raised into it (or where it was), with the same
mixes of lanes. ``warp_total``: a warp whose 32 lanes share a group gives its sum to its first lane and zero to
the others, any other warp each lane its own value; so the values a group's lanes get add up to the group's sum.
``block_max_ints``: every lane of a block gets each entry's largest over the block's lanes, also from a second call
in the same kernel (on the CPU, where a block is one thread, its own values). ``block_reduce_funcs``: every lane gets
each entry's sum or largest with the very bits of ``block_sum`` and ``block_max`` on that entry alone, also from a
second call."""

import functools

import numpy as np
import warp as wp

from warpspring.kernels.linalg import (atomic_raise, atomic_slot, block_max_ints_func, block_reduce_funcs,
                                      reduction_funcs, warp_total_func)


@wp.kernel(enable_backward=False)
def _claim(pattern: wp.array[wp.int32], counts_out: wp.array[wp.int32], slots_out: wp.array[wp.int32]):
    i = wp.tid()
    counter = pattern[i]
    if counter >= 0:  # (lanes with -1 claim nothing: a divergent warp)
        slots_out[i] = atomic_slot(counts_out, counter)
    else:
        slots_out[i] = -1


def test_each_claim_gets_its_own_slot(device):
    rng = np.random.default_rng(3)
    counters, claims = 5, 10_000
    # Runs of one counter (whole warps aggregated), single lanes switching counter, and idle lanes.
    pattern = np.where(rng.random(claims) < 0.3, -1, rng.integers(0, counters, claims))
    pattern[:2048] = np.repeat(np.arange(counters + 3) % counters, 256)[:2048]
    counts = wp.zeros(counters, dtype=wp.int32, device=device)
    slots = wp.zeros(claims, dtype=wp.int32, device=device)
    wp.launch(_claim, dim=claims, inputs=[wp.array(pattern.astype(np.int32), device=device)], outputs=[counts, slots],
              device=device)
    got, ends = slots.numpy(), counts.numpy()
    assert np.all(got[pattern < 0] == -1)
    for c in range(counters):
        mine = np.sort(got[pattern == c])
        np.testing.assert_array_equal(mine, np.arange(len(mine)))  # each slot once, none skipped
        assert ends[c] == len(mine)


@wp.kernel(enable_backward=False)
def _raise(pattern: wp.array[wp.int32], values: wp.array[wp.int32], stored_out: wp.array[wp.int32]):
    i = wp.tid()
    entry = pattern[i]
    if entry >= 0:  # (lanes with -1 raise nothing: a divergent warp)
        atomic_raise(stored_out, entry, values[i])


def test_each_entry_ends_at_the_largest_raised(device):
    rng = np.random.default_rng(5)
    entries, raises = 7, 20_000
    pattern = np.where(rng.random(raises) < 0.3, -1, rng.integers(0, entries, raises))
    pattern[:4096] = np.repeat(np.arange(entries + 9) % entries, 256)[:4096]
    values = rng.integers(-1000, 1_000_000, raises)
    start = np.array([5, 2_000_000, -7, 0, 999_999, 3, 1], dtype=np.int32)  # some above every value raised
    stored = wp.array(start, dtype=wp.int32, device=device)
    wp.launch(_raise, dim=raises, inputs=[wp.array(pattern.astype(np.int32), device=device),
                                          wp.array(values.astype(np.int32), device=device)],
              outputs=[stored], device=device)
    expected = start.copy()
    for e in range(entries):
        if np.any(pattern == e):
            expected[e] = max(start[e], values[pattern == e].max())
    np.testing.assert_array_equal(stored.numpy(), expected)


_LENGTH = 5
_block_max_ints = block_max_ints_func(_LENGTH)
_ints = wp.types.vector(_LENGTH, wp.int32)


@wp.kernel(enable_backward=False)
def _block_maxima(values: wp.array2d[wp.int32], maxima_out: wp.array2d[wp.int32], minima_out: wp.array2d[wp.int32]):
    i = wp.tid()
    mine = _ints()
    for k in range(_LENGTH):
        mine[k] = values[i, k]
    largest = _block_max_ints(mine)
    for k in range(_LENGTH):
        maxima_out[i, k] = largest[k]
        mine[k] = -1 - values[i, k]  # (no overflow: -1 - v is ~v)
    least = _block_max_ints(mine)  # a second call in the same kernel: its shared slots reused
    for k in range(_LENGTH):
        minima_out[i, k] = -1 - least[k]


def test_every_lane_gets_the_block_maxima(device):
    rng = np.random.default_rng(11)
    blocks, lanes = 9, 96  # three warps a block
    values = rng.integers(-2**31, 2**31 - 1, (blocks * lanes, _LENGTH), dtype=np.int64).astype(np.int32)
    values[:lanes, 2] = -5  # one entry equal on every lane
    maxima = wp.zeros((blocks * lanes, _LENGTH), dtype=wp.int32, device=device)
    minima = wp.zeros((blocks * lanes, _LENGTH), dtype=wp.int32, device=device)
    wp.launch(_block_maxima, dim=blocks * lanes, block_dim=lanes,
              inputs=[wp.array(values, dtype=wp.int32, device=device)], outputs=[maxima, minima], device=device)
    if wp.get_device(device).is_cuda:
        per_block = values.reshape(blocks, lanes, _LENGTH)
        np.testing.assert_array_equal(maxima.numpy(), np.repeat(per_block.max(axis=1), lanes, axis=0))
        np.testing.assert_array_equal(minima.numpy(), np.repeat(per_block.min(axis=1), lanes, axis=0))
    else:  # a block is one thread: its own values
        np.testing.assert_array_equal(maxima.numpy(), values)
        np.testing.assert_array_equal(minima.numpy(), values)


_warp_total = warp_total_func(wp.float64)


@wp.kernel(enable_backward=False)
def _totals(values: wp.array[wp.float64], groups: wp.array[wp.int32], totals_out: wp.array[wp.float64]):
    i = wp.tid()
    totals_out[i] = _warp_total(values[i], groups[i])


def test_a_warp_of_one_group_gives_its_sum_to_its_first_lane(device):
    rng = np.random.default_rng(13)
    n = 32 * 10 + 7  # a last warp of 7 lanes
    groups = np.repeat(np.arange(4), 32 * 2)  # warps 0-7 in four groups of two warps each, warp 8 in group 4,
    groups = np.concatenate([groups, [4] * 40, [5] * 23, [6] * 8])  # warp 9 spans groups 4, 5 and 6, warp 10 short
    assert len(groups) == n
    values = rng.integers(-1000, 1000, n).astype(np.float64)  # integers: every order of the sums is exact
    totals = wp.zeros(n, dtype=wp.float64, device=device)
    wp.launch(_totals, dim=n, inputs=[wp.array(values, dtype=wp.float64, device=device),
                                      wp.array(groups.astype(np.int32), device=device)],
              outputs=[totals], device=device, block_dim=64)
    got = totals.numpy()
    if not wp.get_device(device).is_cuda:
        np.testing.assert_array_equal(got, values)
        return
    expected = values.copy()
    for warp in range(n // 32):
        lanes = slice(32 * warp, 32 * warp + 32)
        if len(set(groups[lanes])) == 1:
            expected[lanes] = 0.0
            expected[32 * warp] = values[lanes].sum()
    np.testing.assert_array_equal(got, expected)
    for g in range(7):  # and so each group's values add up to its sum
        assert got[groups == g].sum() == values[groups == g].sum()


@functools.cache
def _reduce_kernel(tiled: bool):
    """Each lane's five values reduced at once (three sums, two largest), twice, and entry by entry."""
    vector, reduce_five = block_reduce_funcs(tiled, 3, 2)
    block_sum, block_max = reduction_funcs(tiled)

    @wp.kernel(enable_backward=False, module="unique")
    def reduce(values: wp.array2d[wp.float64], together_out: wp.array2d[wp.float64],
               again_out: wp.array2d[wp.float64], apart_out: wp.array2d[wp.float64]):
        i = wp.tid()
        mine = vector(values[i, 0], values[i, 1], values[i, 2], values[i, 3], values[i, 4])
        together = reduce_five(mine)
        again = reduce_five(-mine)  # a second call: its shared slots reused
        for k in range(5):
            together_out[i, k] = together[k]
            again_out[i, k] = again[k]
        apart_out[i, 0] = block_sum(values[i, 0])
        apart_out[i, 1] = block_sum(values[i, 1])
        apart_out[i, 2] = block_sum(values[i, 2])
        apart_out[i, 3] = block_max(values[i, 3])
        apart_out[i, 4] = block_max(values[i, 4])

    return reduce


def test_a_vector_reduced_at_once_gets_each_entrys_own_bits(device):
    rng = np.random.default_rng(17)
    blocks, lanes = 7, 96  # three warps a block
    values = rng.normal(0.0, 1.0, (blocks * lanes, 5)) * 10.0 ** rng.integers(-8, 8, (blocks * lanes, 5))
    outs = [wp.zeros((blocks * lanes, 5), dtype=wp.float64, device=device) for _ in range(3)]
    tiled = wp.get_device(device).is_cuda
    wp.launch(_reduce_kernel(tiled), dim=blocks * lanes, block_dim=lanes,
              inputs=[wp.array(values, dtype=wp.float64, device=device)], outputs=outs, device=device)
    together, again, apart = (out.numpy() for out in outs)
    np.testing.assert_array_equal(together, apart)  # the same trees: the same bits
    if not tiled:  # a block is one thread: its own values
        np.testing.assert_array_equal(together, values)
        np.testing.assert_array_equal(again, -values)
        return
    per_block = values.reshape(blocks, lanes, 5)
    sums = np.repeat(per_block[:, :, :3].sum(axis=1), lanes, axis=0)
    np.testing.assert_allclose(together[:, :3], sums, rtol=1e-12, atol=1e-12 * np.abs(per_block).max())
    np.testing.assert_array_equal(together[:, 3:], np.repeat(per_block[:, :, 3:].max(axis=1), lanes, axis=0))
    np.testing.assert_array_equal(again[:, 3:], np.repeat((-per_block[:, :, 3:]).max(axis=1), lanes, axis=0))
    np.testing.assert_array_equal(again[:, :3], -together[:, :3])  # negation commutes with every sum's rounding
