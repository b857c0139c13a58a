"""``kernels/linalg.atomic_slot``: a slot of a list claimed through its counter, warp-aggregated on CUDA. Every claim
gets its own slot, the slots of a counter are exactly 0 … claims − 1, and the counter ends at the claims, also where
only some lanes of a warp claim and neighbouring lanes claim from different counters."""

import numpy as np
import warp as wp

from warpspring.kernels.linalg import atomic_slot


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
