"""The live viewer's cost on a run that writes USD: frames per second with ``run --view`` against without.

The run is the runner's frame loop (``Simulator.step_frame`` then ``UsdWriter.write_frame``, the guard on,
defaults as shipped) on the hanging cloth of ``bench/cloth.py`` at n × n,
16 substeps at 60 fps. With the viewer, a :class:`~warpspring.app.viewer_live.LiveView` is attached (its page
at its default rate, 30 frames/s at most) and a headless client, connected through the guard with the token
and the page's Origin, reads every message the server sends (the count and bytes are reported). The two
configurations alternate ``--repeats`` times in one process after a warm-up run (kernels compiled, graph
captured); the cost is the median over repeats of (wall without / wall with) − 1 in frame rate.

    python bench/viewer.py --device cpu --size 64 --frames 120 --repeats 3 --out bench/results
    python bench/viewer.py --device cuda:0 --size 256 --frames 600 --repeats 5 --pin top --out bench/results
"""

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.app.viewer_live import LiveView
from warpspring.io.usd import UsdWriter


def cloth(n: int, device, pin: str = "corners") -> ws.Model:
    """The hanging cloth of ``bench/cloth.py`` (vertical; ke 1e3 N/m, kd 10 N·s/m, 0.1 kg particles 0.1 m
    apart) at n × n, held by its top corners or (``pin="top"``) its whole top row: from two corners a cloth
    of 256² (6.5 t on two springs) tears past the guard's stretch limit within a second."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 0.05 * n),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=0.1,
                           structural=spring, shear=spring, bend=spring,
                           pin=["top-left", "top-right"] if pin == "corners" else ["top"])
    model = builder.finalize(device)
    model.gravity = (0.0, 0.0, -9.81)
    return model


class HeadlessClient:
    """A WebSocket client of the viewer's page in its own process (as a browser is), reading every message
    through the guard; :meth:`close` returns (messages, bytes) read."""

    def __init__(self, live: LiveView):
        guard = live.viewer.guard
        self.process = subprocess.Popen([sys.executable, __file__, "--client", str(guard.port), guard.token],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def close(self) -> tuple[int, int]:
        out, _ = self.process.communicate("\n", timeout=30)
        messages, size = out.split()
        return int(messages), int(size)


def client(port: int, token: str) -> None:
    """The client process: read every message until a line arrives on stdin; print the count and bytes."""
    import viser
    from websockets.sync.client import connect

    counts = [0, 0]
    socket = connect(f"ws://127.0.0.1:{port}/?token={token}", origin=f"http://127.0.0.1:{port}",
                     subprotocols=[f"viser-v{viser.__version__}"], max_size=None)

    def read():
        try:
            for message in socket:
                counts[0] += 1
                counts[1] += len(message)
        except Exception:  # closed at the end
            pass

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    sys.stdin.readline()
    socket.close()
    thread.join(timeout=5)
    print(counts[0], counts[1])


def run(model: ws.Model, frames: int, folder: str, *, view: bool, rate: float = 30.0) -> dict:
    """One run of ``frames`` frames writing USD, with or without the viewer: wall time [s] of the frames."""
    sim = ws.Simulator(model, fps=60.0, substeps=16)
    live = client = None
    if view:
        live = LiveView(rate=rate).attach(sim)
        client = HeadlessClient(live)
        time.sleep(0.5)  # the client has the page's first state
    path = os.path.join(folder, f"run_{'view' if view else 'plain'}.usdc")
    with UsdWriter(path, model, fps=60.0) as usd:
        usd.write_frame(sim.state)
        wp.synchronize_device(model.device)
        start, cpu = time.perf_counter(), time.process_time()
        for _ in range(frames):
            sim.step_frame()
            usd.write_frame(sim.state)
        wp.synchronize_device(model.device)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    result = {"wall": wall, "fps": frames / wall, "cpu": cpu}
    if view:
        time.sleep(0.3)
        messages, size = client.close()
        result.update(sent=live.sent, dropped=live.dropped, messages=messages, bytes=size)
        live.close()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="folder of the results file (viewer.md, GPU: viewer_gpu.md)")
    parser.add_argument("--pin", choices=("corners", "top"), default="corners",
                        help="what holds the cloth: its top corners (default) or its top row (for long runs at 256²)")
    parser.add_argument("--rate", type=float, default=30.0, help="the page's most frames per second (default 30)")
    parser.add_argument("--client", nargs=2, metavar=("PORT", "TOKEN"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client:
        return client(int(args.client[0]), args.client[1])
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    model = cloth(args.size, device, args.pin)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        run(model, 5, folder, view=True)  # warm-up: kernels, graph, the viewer's imports
        for r in range(args.repeats):
            for view in (False, True) if r % 2 == 0 else (True, False):
                rows.append((view, run(cloth(args.size, device, args.pin), args.frames, folder, view=view, rate=args.rate)))
                print(f"repeat {r + 1}, {'viewer' if view else 'plain '}: {rows[-1][1]['fps']:.2f} frames/s", flush=True)
    plain = [r for v, r in rows if not v]
    viewed = [r for v, r in rows if v]
    wall = [p["fps"] / v["fps"] - 1.0 for p, v in zip(plain, viewed)]
    cpu = [v["cpu"] / p["cpu"] - 1.0 for p, v in zip(plain, viewed)]
    mb = statistics.median(v["bytes"] for v in viewed) / 1e6

    def cells(values, form):
        return ", ".join(form.format(x) for x in values)

    lines = [
        f"# The live viewer's cost on a run that writes USD ({device})",
        "",
        f"`python bench/viewer.py --device {args.device} --size {args.size} --frames {args.frames} "
        f"--repeats {args.repeats} --rate {args.rate:g}"
        + (" --pin top" if args.pin == "top" else "") + f"` on {platform.processor() or platform.machine()} ({os.cpu_count()} CPUs), "
        f"{device}, Warp {wp.__version__}, {datetime.date.today()}: the {args.size}² hanging cloth of bench/cloth.py "
        f"({'held by its top row' if args.pin == 'top' else 'held by its top corners'}), "
        "16 substeps at 60 fps, the guard on, every frame written to USD; with the viewer a headless client in its "
        "own process reads every message through the guard. CPU time is the run's process (simulation, USD, the "
        "viewer's threads); wall time includes waiting for a CPU on a shared machine.",
        "",
        "| run | frames/s (each repeat) | CPU s per run (each repeat) |",
        "|---|---|---|",
        f"| plain | {cells((p['fps'] for p in plain), '{:.2f}')} | {cells((p['cpu'] for p in plain), '{:.2f}')} |",
        f"| with the viewer | {cells((v['fps'] for v in viewed), '{:.2f}')} | "
        f"{cells((v['cpu'] for v in viewed), '{:.2f}')} |",
        "",
        f"Cost per repeat pair, in CPU time (viewed / plain − 1): {cells((100 * x for x in cpu), '{:+.1f} %')}, "
        f"median **{100 * statistics.median(cpu):+.1f} %**; in frame rate (plain / viewed − 1): "
        f"{cells((100 * x for x in wall), '{:+.1f} %')}, median **{100 * statistics.median(wall):+.1f} %**. Frames "
        f"sent to the page per run: {cells((v['sent'] for v in viewed), '{}')} of {args.frames} (the others "
        f"dropped from the view, none from the file); the client read "
        f"{statistics.median(v['messages'] for v in viewed):.0f} messages, {mb:.1f} MB per run (median).",
    ]
    print("\n".join(lines))
    if args.out:
        name = "viewer.md" if device.is_cpu else "viewer_gpu.md"
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, name), "w") as f:
            f.write("\n".join(lines) + "\n")
        print(f"wrote {os.path.join(args.out, name)}")


if __name__ == "__main__":
    main()
