"""Seeds across processes: `gpguided reproduce --coordinator ... --num-processes 2 --process-id I`
on localhost (CPU devices, gloo collectives), against one process with two host devices."""

import os
import socket
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, TWO_DEVICE_ARGS, fast_compile_env

# the group's tests share the fixture two_device_run
pytestmark = [pytest.mark.distributed, pytest.mark.xdist_group("two_devices")]
FIELDS = ("mean_reward", "grad_norm", "exploration_std", "num_basis_vectors", "gp_guard")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _cli(out, *extra):
    return [sys.executable, "-m", "gpguided_jax.cli", *TWO_DEVICE_ARGS, "--out", str(out), *extra]


def _two_processes(out, *extra):
    port = _free_port()
    env = fast_compile_env(level0_only=True)  # compared bit for bit with `two_device_run`
    procs = [subprocess.Popen(_cli(out, "--coordinator", f"localhost:{port}", "--num-processes", "2",
                                   "--process-id", str(i), *extra),
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, e) in zip(procs, outs):
        assert p.returncode == 0, e[-3000:]
    return outs


def test_two_processes_equal_one_process_and_resume_from_a_common_checkpoint(tmp_path,
                                                                            two_device_run):
    """2 processes x 1 device against 1 process x 2 devices, interrupted on the way: both processes
    stop after 2 of 3 chunks (each keeps its own checkpoint); then process
    1 loses its latest checkpoint (as if killed between the two processes' writes). The resumed
    run agrees on the checkpoint both hold and ends with the one-process run's results.npz, bit for
    bit, which process 0 alone reports and writes. (One test for both: each launch of two
    processes is slow.)"""
    out = tmp_path / "run"
    first = _two_processes(out, "--max-chunks", "2")
    assert all("stopped early" in stdout for stdout, _ in first)
    files = set(os.listdir(out))
    assert {"checkpoint_gp_pg.process0-of-2.npz", "checkpoint_gp_pg.process1-of-2.npz"} <= files
    os.remove(out / "checkpoint_gp_pg.process1-of-2.npz")  # its .prev (1 chunk) remains
    second = _two_processes(out)
    (main_out, _), (other_out, _) = second  # process 0 prints the tables and what it wrote
    assert "gp_pg" in main_out and "results.npz" in main_out
    assert "results.npz" not in other_out and "gp_pg" not in other_out  # (gloo's lines only)
    a, b = np.load(out / "results.npz"), np.load(two_device_run / "results.npz")
    for k in FIELDS:
        np.testing.assert_array_equal(a[k], b[k])
