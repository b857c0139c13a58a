"""Shared fixtures: the ``device`` fixture runs a test on the CPU and, where present, on ``cuda:0``.

Kernel compiles are cached per process (and on disk), so tests share compiled modules: keep scene
feature sets (force terms, collider types, precision) few and common across tests.
"""

import pytest
import warp as wp

wp.config.log_level = wp.LOG_WARNING

from helpers import CUDA  # noqa: E402  (after the log level: looking for CUDA initialises Warp)

DEVICES = [pytest.param("cpu", id="cpu")]
if CUDA:
    DEVICES.append(pytest.param("cuda:0", id="cuda", marks=pytest.mark.cuda))


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """A Warp device name: "cpu", and "cuda:0" (marked ``cuda``) when a CUDA device exists."""
    return request.param


@pytest.fixture(params=["float32", "float64"])
def precision(request) -> str:
    """Floating-point precision of a model."""
    return request.param
