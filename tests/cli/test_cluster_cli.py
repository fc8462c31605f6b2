"""Batches on a real Dask cluster: `dask scheduler` and two `dask worker` processes on 127.0.0.1.

One worker is killed (SIGKILL) while it is solving; every image must still be solved exactly once, written
in input order; `--resume` then solves nothing again.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from conftest import DATA, run_cli

distributed = pytest.importorskip("distributed")

REAL = sorted(os.path.join(DATA, "real", f) for f in os.listdir(os.path.join(DATA, "real")) if f.endswith(".tiff"))


def _popen(*args):
    return subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)


@pytest.fixture
def cluster(tmp_path):
    sched_file = tmp_path / "scheduler.json"
    procs = [_popen("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file",
                    str(sched_file))]
    try:
        for _ in range(600):
            if sched_file.exists() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        workers = [_popen("worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard", "--name", f"w{i}",
                          "--death-timeout", "60") for i in range(2)]
        procs += workers
        client = distributed.Client(address, timeout="30s")
        client.wait_for_workers(2, timeout=120)
        yield address, client, workers
        client.close()
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=30)


def test_solve_on_dask_survives_a_killed_worker_and_resumes(cluster, tmp_path):
    address, client, workers = cluster
    images = []
    for k in range(2):                      # the 8 ESA images twice, as 16 distinct files
        for path in REAL:
            dst = tmp_path / f"{k}-{os.path.basename(path)}"
            shutil.copyfile(path, dst)
            images.append(str(dst))
    out = tmp_path / "solved.jsonl"
    env = dict(os.environ)
    env.pop("STARTRACK_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "startrack", "solve", *images, "--scheduler", address, "-o",
                             str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    # Kill the first worker while it holds work.
    victim = None
    deadline = time.time() + 300
    while victim is None and time.time() < deadline and proc.poll() is None:
        processing = client.processing()
        for addr, tasks in processing.items():
            name = client.scheduler_info()["workers"].get(addr, {}).get("name")
            if name == "w0" and tasks:
                victim = addr
        time.sleep(0.05)
    assert victim is not None, "the worker to kill never got a task"
    os.killpg(workers[0].pid, signal.SIGKILL)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    docs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [d["image"]["path"] for d in docs] == images          # each image once, in input order
    assert all(d["solve"]["status"] == "ok" for d in docs), [d["solve"].get("reason") for d in docs]
    # Resume: everything is already there; nothing is solved again and the file is unchanged.
    before = out.read_text()
    again = run_cli("solve", *images, "--scheduler", address, "-o", out, "--resume")
    assert again.returncode == 0, again.stderr
    assert out.read_text() == before
    assert "16 already in the output" in again.stderr


def test_unreadable_path_on_the_workers_is_named(cluster, tmp_path):
    address, _, _ = cluster
    missing = tmp_path / "not-here.tiff"
    proc = run_cli("solve", REAL[0], str(missing), "--scheduler", address, "-o", tmp_path / "o.jsonl")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "not-here.tiff" in lines[0] and "Traceback" not in proc.stderr


def test_local_cluster_solves_in_order(tmp_path):
    out = tmp_path / "o.jsonl"
    proc = run_cli("solve", *REAL[:3], "--scheduler", "local", "-j", "2", "-o", out)
    assert proc.returncode == 0, proc.stderr
    docs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [d["image"]["path"] for d in docs] == REAL[:3]
    assert all(d["solve"]["status"] == "ok" for d in docs)


def test_evaluate_on_a_local_cluster_equals_one_process(tmp_path):
    """The same frames (same seed) give the same table in one process and on a LocalCluster of 2 workers."""
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--size", "1024x1024", "--mag-max", "5.0", "-o", db, "-q", check=True)
    common = ["-d", db, "-a", "pyramid", "--fov-deg", "20", "--size", "1024x1024", "--sigma-px", "0.3",
              "--count", "60", "--seed", "5", "-q"]
    one = run_cli("evaluate", *common, "--json", "-o", tmp_path / "one.json")
    many = run_cli("evaluate", *common, "--scheduler", "local", "-j", "2", "--json", "-o", tmp_path / "many.json")
    assert one.returncode == 0 and many.returncode == 0, many.stderr
    rows_one = json.loads((tmp_path / "one.json").read_text())["rows"]
    rows_many = json.loads((tmp_path / "many.json").read_text())["rows"]
    keys = ("algorithm", "condition", "frames", "success", "failure", "bad", "mean_stars")
    assert [{k: r[k] for k in keys} for r in rows_one] == [{k: r[k] for k in keys} for r in rows_many]


def test_render_on_a_local_cluster_gives_the_same_frames():
    """Chunks rendered by Dask workers carry the same seeds, so the documents are byte for byte the serial ones."""
    args = ["render", "--stars-only", "--count", "40", "--fov-deg", "15", "--size", "1280x960", "--sigma-px", "0.3",
            "--seed", "9", "-q"]
    serial = run_cli(*args)
    cluster = run_cli(*args, "--scheduler", "local", "-j", "2")
    assert serial.returncode == 0 and cluster.returncode == 0, cluster.stderr
    assert serial.stdout == cluster.stdout and serial.stdout.count("\n") == 40
