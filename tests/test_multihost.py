"""`--distributed` with two processes on this machine (CPU collectives over Gloo): the grid spans both
processes' devices, host 0 writes the files, both save their part of each checkpoint, and the run and its resume
give the rows of one process with as many devices, bit for bit."""
import json
import os
import socket
import subprocess
import sys

TINY = ["--preset", "tiny", "--seeds", "2", "--no-progress", "--no-tensorboard"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _train(args: list[str]) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # --cpu-devices decides the split
    return subprocess.Popen([sys.executable, "-m", "ccp_jax.train", *TINY, *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _two_hosts(args: list[str]) -> list[str]:
    """Runs `args` as process 0 and 1 of one distributed run; their outputs."""
    port = _free_port()
    procs = [_train(["--distributed", "--coordinator", f"localhost:{port}", "--num-processes", "2",
                     "--process-id", str(i), "--cpu-devices", "1", *args]) for i in range(2)]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out[-3000:]
    return outs


def _rows(run) -> list[dict]:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "epoch_wall_s"} for line in lines]


def test_two_processes_train_and_resume_as_one_process_with_two_devices(tmp_path):
    multi, single = tmp_path / "multi", tmp_path / "single"
    outs = _two_hosts(["--total-steps", "400", "--checkpoint-every", "1", "--out", str(multi)])
    assert all("on 2 cpu devices" in out for out in outs)  # one device per process, one mesh
    _two_hosts(["--resume", str(multi), "--total-steps", "600"])
    one = _train(["--cpu-devices", "2", "--total-steps", "600", "--out", str(single)])
    out = one.communicate(timeout=600)[0]
    assert one.returncode == 0, out[-3000:]
    assert [r["epoch"] for r in _rows(multi)] == [1, 1, 2, 2, 3, 3]  # written once, by host 0
    assert _rows(multi) == _rows(single)
    summary = json.loads((multi / "summary.json").read_text())
    assert [m["epochs"] for m in summary["members"]] == [3, 3]
