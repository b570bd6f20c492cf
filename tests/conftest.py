"""Shared models for the rcotorch tests."""

import os
import signal
import time
from pathlib import Path

import control
import numpy as np
import pytest
import torch

import rcotorch as rt

# The tests use small tensors; on a 2-core machine extra threads cost more than they give.
torch.set_num_threads(1)

# Measured data sets: the local copy beside the checkout (as in CI) stands in for the download.
LOCAL_SILVERBOX = Path(__file__).resolve().parents[2] / "shared" / "data" / "silverbox"
if LOCAL_SILVERBOX.is_dir():
    os.environ.setdefault("RCOTORCH_SILVERBOX", str(LOCAL_SILVERBOX))


@pytest.fixture(scope="session")
def silverbox_csv() -> Path:
    """The verified SNLS80mV.csv of the Silverbox benchmark (skips the test where it cannot be had)."""
    try:
        return rt.datasets.silverbox_files()["SNLS80mV.csv"]
    except rt.DataError as e:
        pytest.skip(f"the Silverbox data set is not available here: {e}")

SDOF_A = [[0.0, 1.0], [-30.0, -5.0]]     # m = 1, k = 30, c = 5; states (q, v)
SDOF_B = [[0.0, 0.0], [1.0, 1.0]]        # inputs w (exogenous force), u (force of the unknown subsystem)


@pytest.fixture
def sdof_known():
    """Factory for the SDOF known model of the seed paper, ZOH-discretized at ``dt``.

    ``output='velocity'`` measures v and feeds v to the unknown subsystem (y = y0 = v); ``'position'`` uses q.
    """

    def make(dt=0.1, output="velocity", name="known"):
        C = [[0.0, 1.0], [0.0, 1.0]] if output == "velocity" else [[1.0, 0.0], [1.0, 0.0]]
        sys = control.ss(SDOF_A, SDOF_B, C, np.zeros((2, 2)))
        return rt.LTI.from_control(sys, inputs=["w", "u"], outputs=["y", "y0"], dt=dt, name=name)

    return make


@pytest.fixture
def zoh_first_order():
    """Factory for ZOH(10 / (s + 2)) at ``dt`` as an LTI block with ports in -> out (the SDOF's unknown part)."""

    def make(dt=0.1):
        return rt.LTI.from_control(control.tf([10.0], [1.0, 2.0]), inputs=["in"], outputs=["out"], dt=dt)

    return make


def default_signals() -> None:
    """Give a subprocess the default SIGINT, SIGTERM and SIGHUP (``preexec_fn``): a test run started under nohup or
    in the background of a shell inherits them ignored, and a run leaves an ignored signal ignored."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def wait_for(predicate, timeout: float = 120.0) -> None:
    """Poll ``predicate()`` until it is true (a subprocess reached some state), or fail after ``timeout`` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError("timed out")


def at_step(monkeypatch, step: int, action) -> None:
    """Do ``action(out)`` once, when the run reaches ``step`` (a fault injected into a running run)."""
    import rcotorch.run.runner
    original, done = rcotorch.run.runner.Run._take_snapshot, []

    def snapshot(self):
        if self.k >= step and not done:
            done.append(action(self.out))
        return original(self)
    monkeypatch.setattr(rcotorch.run.runner.Run, "_take_snapshot", snapshot)
