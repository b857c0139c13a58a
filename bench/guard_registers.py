"""The registers a thread of each of the guard's kernels (and of the step they ride on) gets on a CUDA architecture,
without a GPU: the kernels a run of ``guard_cost.py``'s cloth launches are built as they are for CUDA (the check's
passes tiled) and compiled for ``--arch`` with Warp's NVRTC (``wp.compile_aot_module``); the count is read from each
cubin (its ``EIATTR_REGCOUNT``), and the bytes of local memory a thread's frame takes (``EIATTR_FRAME_SIZE``: what
the compiler spilled, with any local arrays). Registers decide a kernel's occupancy: 2,048 resident threads and 65,536 registers a
multiprocessor on sm_90, so more than 128 registers a thread leaves at most 512 threads (25 %) resident, ≤ 64 all.

    python bench/guard_registers.py --size 64 --integrator symplectic_euler
"""

from __future__ import annotations

import argparse
import struct
import tempfile
from pathlib import Path

import warp as wp

import warpspring as ws
import warpspring.core.guards as guards_module
import warpspring.core.integrators.symplectic_euler as se_module
from guard_cost import SUBSTEPS, hanging_cloth
from warpspring.core.guards import WATCH_FRAMES

EIATTR_REGCOUNT, EIATTR_FRAME_SIZE, EIFMT_SVAL = 0x2F, 0x11, 0x04


def register_counts(cubin: Path, attribute_wanted: int = EIATTR_REGCOUNT) -> dict[int, int]:
    """Registers per thread (or with ``EIATTR_FRAME_SIZE`` the local frame's bytes) of each function of ``cubin`` by
    its symbol index (the ``.nv.info`` attributes)."""
    data = cubin.read_bytes()
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + k * shentsize) for k in range(shnum)]
    names = sections[shstrndx][4]
    counts = {}
    for section in sections:
        name = data[names + section[0]:data.index(b"\0", names + section[0])]
        if name != b".nv.info":
            continue
        offset, size, k = section[4], section[5], 0
        while k < size:
            fmt, attribute, length = struct.unpack_from("<BBH", data, offset + k)
            k += 4
            if fmt == EIFMT_SVAL:
                if attribute == attribute_wanted:
                    symbol, value = struct.unpack_from("<II", data, offset + k)
                    counts[symbol] = value
                k += length
    return counts


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--integrator", default="symplectic_euler")
    parser.add_argument("--arch", type=int, default=90)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    built = {}

    def recording(name, factory, tiled_at=None):
        def make(*a, **k):
            if tiled_at is not None:  # the CUDA variant: the check's passes tiled
                a = a[:tiled_at] + (True,) + a[tiled_at + 1:]
            kernels = factory(*a, **k)
            for kernel in kernels if isinstance(kernels, tuple) else (kernels,):
                built[kernel.module.name] = kernel
            if tiled_at is None:
                return kernels
            return factory(*a[:tiled_at] + (False,) + a[tiled_at + 1:], **k)  # what runs here, on the CPU
        return make

    guards_module.guard_kernels = recording("guard", guards_module.guard_kernels, tiled_at=2)
    guards_module.guard_energy_kernel = recording("energy", guards_module.guard_energy_kernel, tiled_at=2)
    se_module.symplectic_euler_kernel = recording("step", se_module.symplectic_euler_kernel)
    se_module.symplectic_euler_frame_kernel = recording("frame", se_module.symplectic_euler_frame_kernel)
    if hasattr(se_module, "symplectic_euler_blocks_kernel"):
        se_module.symplectic_euler_blocks_kernel = recording("blocks", se_module.symplectic_euler_blocks_kernel, tiled_at=4)
    model = hanging_cloth(args.size, "cpu", evaluation="gather")
    options = {"cpu_sweep": False} if args.integrator == "symplectic_euler" else {}
    for guard in (None, ws.GuardLimits()):
        for one_launch in ((False, True) if args.integrator == "symplectic_euler" else (None,)):
            if one_launch is not None:
                options["one_launch"] = one_launch
            sim = ws.Simulator(model, fps=60, substeps=SUBSTEPS, guard=guard, use_graph=False,
                               integrator=ws.make_integrator(args.integrator, model, **options))
            for _ in range(WATCH_FRAMES + 2):  # past the frames a guard watches from the start: its steady frames
                sim.step_frame()
    print(f"{args.size}², {args.integrator}: registers a thread on sm_{args.arch} (NVRTC, Warp {wp.config.version})")
    print("| kernel | registers | local frame [B] |\n|---|---|---|")
    import os
    with tempfile.TemporaryDirectory() as folder:
        folder = os.environ.get("KEEP_AOT", folder)
        for key, kernel in sorted(built.items()):
            for path in wp.compile_aot_module(kernel.module, device=None, arch=args.arch, module_dir=folder,
                                              use_ptx=False):
                if str(path).endswith(".cubin"):
                    counts = register_counts(Path(path))
                    frames = register_counts(Path(path), EIATTR_FRAME_SIZE)
                    print(f"| {kernel.key.split('__locals__')[-1][:40]} ({key[-8:]}) | {max(counts.values(), default=0)} "
                          f"| {max(frames.values(), default=0)} |")


if __name__ == "__main__":
    main()
