"""Build every example's USD at two revisions on the CPU and check that their points and velocities are
bit-identical: the check a change that claims to move code without changing what it computes must pass.

    python tools/compare_examples.py                      # 3987b38 against the working tree
    python tools/compare_examples.py --base main~3 --head HEAD --frames 60

Each revision runs from its own checkout (a temporary ``git worktree`` for a commit; the working tree itself
for ``--head WORKTREE``), as ``python -m warpspring run`` for the scene files and as the scripts' own
``--stage-path`` option for the Python examples, so each imports its own copy of the package. Every time
sample of every ``points`` and ``velocities`` attribute in the two files must hold the same float bits
(compared as integers, so -0.0 and 0.0, or two NaNs with different payloads, count as different).
Exit status 0 when every example matches, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCRIPT_EXAMPLES = ("hanging_cloth.py", "cloth_on_sphere.py", "swinging_cloth.py")
NOT_SCENES = ("sweep.toml",)  # a sweep file, not a scene: `warpspring sweep` reads it


def examples() -> list[Path]:
    tomls = sorted(p for p in (ROOT / "examples").glob("*.toml") if p.name not in NOT_SCENES)
    return tomls + [ROOT / "examples" / name for name in SCRIPT_EXAMPLES]


def checkout(ref: str, scratch: Path) -> Path:
    """A checkout of ``ref``: the working tree itself for WORKTREE, else a detached temporary worktree."""
    if ref == "WORKTREE":
        return ROOT
    path = scratch / f"tree-{ref.replace('/', '_').replace('~', '_')}"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(path), ref], check=True,
                   capture_output=True)
    return path


def build(tree: Path, example: Path, out: Path, frames: int) -> str | None:
    """Run one example from ``tree``; returns an error text, or None when the file was written."""
    env = dict(os.environ, PYTHONPATH=str(tree), WARP_CACHE_PATH=os.environ.get("WARP_CACHE_PATH", ""))
    if not env["WARP_CACHE_PATH"]:
        env.pop("WARP_CACHE_PATH")
    source = tree / "examples" / example.name
    if example.suffix == ".toml":
        command = [sys.executable, "-m", "warpspring", "run", str(source), "-o", str(out), "--device", "cpu", "-q"]
        if frames:
            command += ["--frames", str(frames)]
    else:
        command = [sys.executable, str(source), "--device", "cpu", "--stage-path", str(out)]
        if frames:
            command += ["--num-frames", str(frames)]
    result = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    if result.returncode != 0 or not out.exists():
        return f"exit {result.returncode}: {(result.stderr or result.stdout).strip().splitlines()[-1:]}"
    return None


def samples(path: Path) -> dict[tuple[str, str, str], np.ndarray]:
    """Every time sample of every points/velocities attribute: (prim path, attribute, time) → float bits."""
    from pxr import Usd  # optional: usd-core

    stage = Usd.Stage.Open(str(path))
    found = {}
    for prim in stage.Traverse():
        for name in ("points", "velocities"):
            attribute = prim.GetAttribute(name)
            if not attribute or not attribute.HasAuthoredValue():
                continue
            times = attribute.GetTimeSamples() or [Usd.TimeCode.Default()]
            for t in times:
                value = np.asarray(attribute.Get(t), dtype=np.float32)
                key = (str(prim.GetPath()), name, "default" if isinstance(t, Usd.TimeCode) else f"{float(t):g}")
                found[key] = value.view(np.uint32).copy()
    return found


def compare(a: Path, b: Path) -> tuple[bool, str]:
    first, second = samples(a), samples(b)
    if not first:
        return False, "no points or velocities in the base file"
    if first.keys() != second.keys():
        missing = sorted(set(first) ^ set(second))[:3]
        return False, f"different samples ({len(first)} against {len(second)}; e.g. {missing})"
    for key, value in first.items():
        other = second[key]
        if value.shape != other.shape or not np.array_equal(value, other):
            differs = int((value != other).sum()) if value.shape == other.shape else "shape"
            return False, f"{key[0]}.{key[1]} at time {key[2]}: {differs} values differ"
    frames = len({k[2] for k in first})
    return True, f"{len(first)} samples over {frames} time codes identical"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", default="3987b38", help="the revision to compare against (a commit, or WORKTREE)")
    parser.add_argument("--head", default="WORKTREE", help="the revision under test (a commit, or WORKTREE)")
    parser.add_argument("--frames", type=int, default=12,
                        help="frames per example (0: each example's own length; slow on the CPU)")
    parser.add_argument("--only", nargs="*", default=None, help="example file names to run (default: all)")
    args = parser.parse_args(argv)
    chosen = [e for e in examples() if args.only is None or e.name in args.only or e.stem in args.only]
    failures = 0
    with tempfile.TemporaryDirectory(prefix="compare-examples-") as scratch_name:
        scratch = Path(scratch_name)
        trees = {}
        try:
            for role, ref in (("base", args.base), ("head", args.head)):
                trees[role] = checkout(ref, scratch)
            for example in chosen:
                outs = {role: scratch / f"{role}-{example.stem}.usdc" for role in trees}
                errors = {role: build(trees[role], example, outs[role], args.frames) for role in trees}
                if any(errors.values()):
                    failures += 1
                    print(f"FAIL {example.name}: " + "; ".join(f"{r}: {e}" for r, e in errors.items() if e))
                    continue
                same, what = compare(outs["base"], outs["head"])
                failures += not same
                print(f"{'same' if same else 'DIFF'} {example.name}: {what}", flush=True)
        finally:
            for role, tree in trees.items():
                if tree != ROOT:
                    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                                   capture_output=True)
    print(f"{len(chosen) - failures} of {len(chosen)} examples bit-identical ({args.base} against {args.head})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
