"""A property-based fuzz test of the scene format: every scene hypothesis makes from a small valid one — keys
of the schema set to adversarial values (wrong types, NaN, ±∞, extreme integers, nested lists and tables,
odd strings), keys deleted, unknown keys added — runs through ``warpspring run`` and ends with exit status 0
(it ran), 2 (refused) or 3 (a guard stopped it), with at most one error line on stderr: no traceback, no
hang, no signal, no NumPy overflow warning (a value past the checks).

Derandomized (the same examples on every run, so CI is reproducible), at most ``EXAMPLES`` examples within
``TIME_BUDGET`` seconds; each runs in this process (``main(argv)``, stderr captured) under a wall-clock deadline (``DEADLINE`` seconds,
SIGALRM), so a hang fails its example instead of stalling the suite. Failures found are pinned below as
``@example``s (the scene that failed, with what it broke in a comment).
"""

import contextlib
import io
import math
import os
import signal
import sys
import time
import warnings

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from helpers import deadline  # noqa: E402
from warpspring.app.cli import EXIT_CONFIG, EXIT_SIMULATION, main  # noqa: E402
from warpspring.io.scene_schema import (EMITTER, QUATERNION, SCHEMA, SOFT_BODY, VECTOR, Live, Number,  # noqa: E402
                                        PerWorld, Since, Tables, TrackTable)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

pytestmark = pytest.mark.skipif(not hasattr(signal, "setitimer"), reason="the per-example deadline uses SIGALRM")

#: Examples per run (the issue's budget: ≤ 100 examples, ≤ 90 s in all; measured: see the report).
EXAMPLES = 100
#: Wall seconds of fuzzing after which the remaining generated examples return at once (the issue's 90 s in
#: all; a warm kernel cache runs the 100 in ~17 s on a 2-core CPU, a cold one compiles the variants reached).
TIME_BUDGET = 75.0
_clock: dict[str, float] = {}  # when the first example started
#: Wall seconds one example may take (a first run compiles the kernels of the variants it reaches): past it the
#: example fails as a hang.
DEADLINE = 60.0

#: The scene every example starts from: 9 particles, one frame of two steps, a sphere below.
BASE = {
    "version": 2,
    "simulation": {"fps": 60.0, "frames": 1, "substeps": 2},
    "world": {"gravity": [0.0, 0.0, -9.81]},
    "cloth": {"grid": {"nx": 3, "ny": 3, "spacing": 0.1}, "particle_mass": 0.1, "pin": ["top-left"],
              "structural": {"ke": 100.0, "kd": 0.1}, "bend": False},
    "collider": [{"type": "sphere", "center": [0.0, 0.0, -0.5], "radius": 0.2}],
}

#: Every key path a mutation may set or delete: the schema's tables and keys, a cloth's spring tables, an
#: emitter's and a soft body's keys.
PATHS = sorted(
    [(table,) for table in SCHEMA] + [("emitter",), ("soft_body",)]
    + [(table, key) for table, keys in SCHEMA.items() for key in keys]
    + [("cloth", family, key) for family in ("structural", "shear", "bend") for key in ("ke", "kd")]
    + [("cloth", "grid", key) for key in ("nx", "ny", "spacing")]
    + [("emitter", key) for key in EMITTER] + [("soft_body", key) for key in SOFT_BODY]
)

#: Finite values in range for most keys, of extreme magnitudes: they pass the type checks and reach the builder,
#: the advisor and the run.
_finite = st.sampled_from([0.0, 1e-300, 1e-30, 1e-9, 1e-3, 0.05, 0.5, 1.0, 3.0, 1e3, 1e9, 1e18, 1e30, 1e300])
_numbers = st.one_of(
    _finite, _finite, _finite,
    st.sampled_from([1, 2, 3, 4, 0]), st.sampled_from([1, 2, 3, 4, 0]),
    st.sampled_from([-1, 2**31, 2**63 - 1, -2**63, 10**30]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([-0.0, -1e18, float("nan"), float("inf"), -float("inf")]),
)
_strings = st.one_of(
    st.sampled_from(["", "top-left", "symplectic_euler", "rk4", "implicit_euler", "float64", "Y", "Z", "world",
                     "sphere", "box", "plane", "ground", "capsule", "mesh", "cpu", "cuda:7", "/", "..", "\x00",
                     "nowhere.obj", "a" * 300]),
    st.text(max_size=8),
)
_leaves = st.one_of(st.booleans(), _numbers, _strings)
VALUES = st.recursive(_leaves, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.sampled_from(["a", "ke", "nx", "x", "times",
                                                                                        "values", "type"]),
                                                                       inner, max_size=3)),
                      max_leaves=10)
_vectors = (st.lists(_numbers, min_size=2, max_size=5) | st.lists(_finite, min_size=3, max_size=3)
            | st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
_tracks = st.fixed_dictionaries({"times": st.lists(_numbers, max_size=4), "values": st.lists(_numbers | _vectors,
                                                                                              max_size=4)},
                                optional={"interpolation": _strings, "extrapolation": _strings})


def typed(spec) -> st.SearchStrategy:
    """Values of the kind ``spec`` (a schema entry) asks for, extreme ones among them (so that they reach past
    the type checks into the range checks and the builder)."""
    if isinstance(spec, Since):
        return typed(spec.spec)
    if isinstance(spec, Number):
        return _numbers
    if spec == VECTOR:
        return _vectors
    if spec == QUATERNION:
        return st.lists(_numbers, min_size=3, max_size=5)
    if isinstance(spec, Live):
        return typed(spec.value) | _tracks
    if isinstance(spec, PerWorld):
        return st.lists(typed(spec.value), max_size=3)
    if isinstance(spec, TrackTable):
        return _tracks
    if isinstance(spec, Tables):
        return st.fixed_dictionaries({}, optional={k: typed(v) for k, v in spec.schema.items()})
    if spec is bool:
        return st.booleans()
    if spec is str:
        return _strings
    if spec is list:
        return st.lists(_numbers | _strings | _vectors, max_size=4)
    if isinstance(spec, dict):
        return st.fixed_dictionaries({}, optional={k: typed(v) for k, v in spec.items()})
    return VALUES


def _spec(path):
    table = {"emitter": EMITTER, "soft_body": SOFT_BODY}.get(path[0], SCHEMA.get(path[0], {}))
    if len(path) == 2:
        return table.get(path[1])
    if len(path) == 3 and path[1] == "grid":
        return Number(1, integer=True) if path[2] in ("nx", "ny") else Number(0.0, inclusive=False)
    if len(path) == 3:
        return Number(0.0)
    return table


_set_typed = st.sampled_from(PATHS).flatmap(lambda path: st.tuples(st.just("set"), st.just(path),
                                                                   typed(_spec(path))))
MUTATIONS = st.lists(st.one_of(
    _set_typed, _set_typed, _set_typed, _set_typed, _set_typed, _set_typed,
    st.tuples(st.just("set"), st.sampled_from(PATHS), VALUES),
    st.tuples(st.just("delete"), st.sampled_from(PATHS), st.none()),
    st.tuples(st.just("set"), st.tuples(st.sampled_from(sorted(SCHEMA)), st.text(min_size=1, max_size=6)), VALUES),
), min_size=1, max_size=3)


def mutate(mutations) -> dict:
    """BASE with the mutations applied (a path through a list enters its first table)."""
    scene = _copy(BASE)
    for action, path, value in mutations:
        table = scene
        for key in path[:-1]:
            node = table.get(key)
            if isinstance(node, list) and node and isinstance(node[0], dict):
                node = node[0]
            if not isinstance(node, dict):
                node = {}
                table[key] = node
            table = node
        if action == "set":
            table[path[-1]] = value
        else:
            table.pop(path[-1], None)
    return scene


def _copy(value):
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


def toml(scene: dict) -> str:
    """``scene`` as TOML text: its tables as inline tables of one top-level assignment each (TOML allows any
    value there, so every generated value can be written; a value TOML cannot hold, None, is left out)."""
    return "".join(f"{_key(key)} = {_value(value)}\n" for key, value in scene.items() if value is not None)


def _key(key: str) -> str:
    return key if key and all(c.isalnum() or c in "_-" for c in key) and key.isascii() else _string(key)


def _string(text: str) -> str:
    return '"' + "".join(c if c.isprintable() and c not in '"\\' else f"\\u{ord(c):04x}" if ord(c) < 0x10000
                         else f"\\U{ord(c):08x}" for c in text) + '"'


def _value(value) -> str:
    if isinstance(value, tuple) and value[:1] == ("raw",):  # a pinned example's text, as it is
        return value[1]
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value) if -2**63 <= value < 2**63 else repr(float(value))
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value if v is not None) + "]"
    return "{" + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items() if v is not None) + "}"


class Hang(Exception):
    """An example ran past DEADLINE."""



def run_scene_text(text: str, folder) -> tuple[int, list[str]]:
    """The exit status and stderr's lines of ``warpspring run`` on ``text``; a RuntimeWarning (NumPy's overflow
    or invalid value: a value that leaked past the checks; on the command line two lines of noise on stderr)
    counts as a line of its own."""
    scene = os.path.join(folder, "scene.toml")
    with open(scene, "w", encoding="utf-8") as f:
        f.write(text)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), deadline(DEADLINE, Hang), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status = main(["run", scene, "-o", os.path.join(folder, "out.usdc"), "--device", "cpu", "-q",
                       "--watch-every", "0"])
    leaked = [f"RuntimeWarning: {w.message} ({os.path.basename(w.filename)})" for w in caught
              if issubclass(w.category, RuntimeWarning)]
    return status, err.getvalue().splitlines() + leaked


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return str(tmp_path_factory.mktemp("fuzz"))


@settings(max_examples=EXAMPLES, derandomize=True, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(mutations=MUTATIONS)
# The adversarial pass of the issue: inline tables nested 400 deep (a RecursionError traceback) ...
@example(mutations=[("set", ("cloth", "grid"), ("raw", "{a = " * 400 + "1" + "}" * 400))])
@example(mutations=[("set", ("world", "gravity"), ("raw", "[" * 3000 + "]" * 3000))])
# ... and an absurd stiffness on the tiny cloth (the advisor's dry run ran for minutes).
@example(mutations=[("set", ("cloth", "shear"), {"ke": 1e18})])
# Found by this test: a float32 scene's wind lift of 1e300 became infinite on the device (NumPy's overflow
# warning, then an internal "omega_max must be a finite number" error naming no key).
@example(mutations=[("set", ("wind", "lift"), 1e300)])
@example(mutations=[("set", ("cloth", "structural"), {"ke": 1e39, "kd": 0.1})])
def test_every_scene_ends_cleanly(folder, mutations):
    if time.monotonic() - _clock.setdefault("start", time.monotonic()) > TIME_BUDGET:
        return  # past the budget: the pinned examples (run first) and those before have run
    text = toml(mutate(mutations))
    status, err = run_scene_text(text, folder)
    errors = [line for line in err if not line.startswith("warpspring: warning")]
    assert status in (0, EXIT_CONFIG, EXIT_SIMULATION), (status, err, text)
    assert len(errors) <= 1 and not any("Traceback" in line for line in err), (err, text)


def test_the_writer_round_trips():
    """The TOML writer the fuzz test relies on: BASE and a value of every kind come back as written."""
    scene = mutate([("set", ("world", "drag"), [1, 2.5, "a\"\n", {"x": True}]),
                    ("set", ("guard", "every"), float("inf"))])
    parsed = tomllib.loads(toml(scene))
    assert parsed["world"]["drag"] == [1, 2.5, "a\"\n", {"x": True}] and parsed["guard"]["every"] == float("inf")
    assert parsed["cloth"] == BASE["cloth"] and parsed["collider"] == BASE["collider"]
