"""An ensemble over two real processes (JAX's distributed runtime, two CPU
devices each, gloo collectives) against one process with the same four
devices: the same final states and largest energy error bit for bit, a
batch loss and its gradient to round-off (the cross-process sums add in
another order). A process that passes the wrong rows, none, or dies is
caught. The workers: tests/ensemble_worker.py."""

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
WORKER = ROOT / "tests" / "ensemble_worker.py"
TIMEOUT_S = 240


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _launch(processes: int, devices: int, out: Path, fault: str = "none") -> list[subprocess.CompletedProcess]:
    port = _free_port()
    started = [
        subprocess.Popen(
            [sys.executable, str(WORKER), "--processes", str(processes), "--process-id", str(i), "--port", str(port)]
            + ["--devices", str(devices), "--out", str(out), "--fault", fault],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(processes)
    ]
    finished = []
    deadline = time.monotonic() + TIMEOUT_S
    for proc in started:
        try:
            stdout, stderr = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            for p in started:
                p.kill()
            pytest.fail(f"an ensemble worker ({processes} processes, fault {fault!r}) hung past {TIMEOUT_S} s")
        finished.append(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr))
    return finished


def _ran(runs: list[subprocess.CompletedProcess]) -> None:
    for run in runs:
        assert run.returncode == 0, run.stderr[-3000:]


def _differences(a: Path, b: Path) -> dict[str, float]:
    """Largest |difference| of each gathered result of two runs."""
    x, y = np.load(a / "gathered.npz"), np.load(b / "gathered.npz")
    return {k: float(np.max(np.abs(x[k] - y[k]))) if x[k].shape == y[k].shape else np.inf for k in x.files}


@pytest.fixture(scope="module")
def single_process(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("one_process")
    _ran(_launch(1, 4, out))
    return out


def test_two_processes_equal_one(tmp_path, single_process):
    _ran(_launch(2, 2, tmp_path))
    differences = _differences(tmp_path, single_process)
    for key in ("scan_attitude", "scan_moment", "diffrax_attitude", "diffrax_moment", "worst_energy"):
        assert differences[key] == 0.0, (key, differences)
    # Sums over the batch cross processes in another order: round-off.
    reference = np.load(single_process / "gathered.npz")
    for key in ("loss", "grad"):
        assert differences[key] <= 1e-13 * np.max(np.abs(reference[key])), (key, differences)
    gathered = np.load(tmp_path / "gathered.npz")
    assert 0 < gathered["worst_energy"] < 1e-12  # a conservation law, computed across both processes
    # Each process's local rows are its block of the gathered batch, and its input rows.
    for process in (0, 1):
        mine = np.load(tmp_path / f"local_{process}.npz")
        rows = slice(4 * process, 4 * process + 4)
        np.testing.assert_array_equal(mine["scan_moment"], gathered["scan_moment"][rows])
        np.testing.assert_array_equal(mine["scan_attitude"], gathered["scan_attitude"][rows])
        np.testing.assert_array_equal(mine["y0_moment"], gathered["all_moments"][rows])
        assert mine["worst_energy"] == gathered["worst_energy"]


def test_a_duplicated_part_is_seen(tmp_path, single_process):
    _ran(_launch(2, 2, tmp_path, fault="duplicate"))
    differences = _differences(tmp_path, single_process)
    assert differences["scan_moment"] > 1e-3 and differences["scan_attitude"] > 1e-3, differences


def test_a_dropped_part_is_refused_in_every_process(tmp_path):
    runs = _launch(2, 2, tmp_path, fault="drop")
    for run in runs:
        assert run.returncode != 0
        assert "every process must pass the same number of rows to shard_batch" in run.stderr
        assert "process 0: 4, process 1: 0" in run.stderr


def test_a_dead_process_ends_the_run(tmp_path):
    started = time.monotonic()
    runs = _launch(2, 2, tmp_path, fault="crash")
    assert time.monotonic() - started < TIMEOUT_S
    assert "process 1 stops on purpose" in runs[1].stderr
    # The survivor does not hang: the runtime's shutdown barrier times out
    # and ends it with an error.
    assert runs[0].returncode != 0, runs[0].stderr[-3000:]
    assert not (tmp_path / "gathered.npz").exists()
