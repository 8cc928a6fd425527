"""Ray (`kgs_app.cluster`) and CPU placement (`kgs_core.threads`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from kgs_core.threads import SPIN_COUNT, configure_process, cores_available, placement_env, requested_cores


def sweep(scene_dir, root, seeds=(0, 1), iterations=40):
    """Two small trainings (one per seed) of the tiny synthetic scene, not yet run."""
    from kgs_core.data.formats import load_scene
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    scene = load_scene(scene_dir)
    return [
        Trainer(
            scene,
            root / f"s{seed}",
            make_config(
                "fast", iterations=iterations, eval_every=20, seed=seed, checkpoint_every=1000, decompose_at=20, **{"densify.start": 10}
            ),
            progress=False,
        )
        for seed in seeds
    ]


def results(trainers) -> list[str]:
    """What must not depend on where a run was trained: its log (losses, PSNR) and final state,
    as JSON (NaN, the loss before the first step, compares equal there)."""
    from kgs_core.run import read_log

    keep = ("iteration", "gaussians", "dynamic_share", "final_psnr_heldout")
    return [
        json.dumps(
            {"info": {k: t.info[k] for k in keep}, "log": [{k: v for k, v in r.items() if "seconds" not in k} for r in read_log(t.run_dir)]}
        )
        for t in trainers
    ]


def test_a_ray_sweep_equals_the_same_sweep_trained_in_turn(tiny_run, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is the optional [cluster] extra")
    import torch

    from kgs_app.cluster import connect, run_trainers

    scene_dir = tiny_run.parent.parent / "scenes" / "bounce"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a task of one CPU runs one thread; float sums depend on how work is split between threads
    try:
        local = sweep(scene_dir, tmp_path / "local")
        for t in local:
            t.run()
    finally:
        torch.set_num_threads(threads)
    connect(None, num_cpus=2)
    try:
        remote = sweep(scene_dir, tmp_path / "ray")
        nodes = run_trainers(remote, None, task_cpus=1)
    finally:
        ray.shutdown()
    assert len(nodes) == 2 and all("cores" in n for n in nodes)
    assert all((t.run_dir / "model.pt").is_file() for t in remote)  # the tasks wrote the runs
    assert results(remote) == results(local)
    assert results(local)[0] != results(local)[1]  # the seeds differ: the comparison can fail


def test_without_ray_flag_nothing_imports_ray(tmp_path):
    code = (
        "import sys, kgs_app.cli as c, kgs_app.bench.quality, kgs_app.bench.real, kgs_app.cluster; "
        "c.build_parser(); print('ray' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_missing_ray_is_a_clear_error(tiny_run, tmp_path, monkeypatch, capsys):
    from kgs_app.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    scene = tiny_run.parent.parent / "scenes" / "bounce"
    assert main(["train-many", str(scene), "--out", str(tmp_path / "o"), "--iterations", "5", "--ray"]) == 2
    assert "pip install 'kinematics-gs[cluster]'" in capsys.readouterr().err
    assert not (tmp_path / "o" / "runs").exists()  # nothing trained, nothing half-written


def test_train_many_trains_every_combination_in_turn(tiny_run, tmp_path, capsys):
    from kgs_app.cli import main

    scene = tiny_run.parent.parent / "scenes" / "bounce"
    out = tmp_path / "many"
    assert main(["train-many", str(scene), "--out", str(out), "--configs", "full,decompose", "--seeds", "0,1", "--iterations", "8"]) == 0
    rows = json.loads((out / "train-many.json").read_text())
    names = sorted(p.name for p in (out / "runs").iterdir())
    assert names == sorted(f"bounce-fast-{c}-s{s}" for c in ("full", "no_decomposition_D3DGS-like") for s in (0, 1))
    assert len(rows) == 4 and all(r["iterations"] == 8 for r in rows)
    assert all(json.loads((out / "runs" / n / "run.json").read_text())["config"]["seed"] == int(n[-1]) for n in names)
    assert (
        main(["train-many", str(scene), "--out", str(out), "--iterations", "8", "--seeds", "0", "--configs", "decompose"]) == 2
    )  # the run exists: refused, nothing overwritten
    assert "exists" in capsys.readouterr().err


def test_placement_environment(monkeypatch):
    assert placement_env(3) == {"OMP_NUM_THREADS": "3", "GOMP_SPINCOUNT": str(SPIN_COUNT)}
    assert placement_env(0)["OMP_NUM_THREADS"] == "1"
    assert 1 <= cores_available() <= (os.cpu_count() or 1)
    for raw, want in (("4", 4), ("off", None), ("", None), ("-1", None), ("x", None)):
        monkeypatch.setenv("KGS_THREADS", raw)
        assert requested_cores() == want
    monkeypatch.setenv("KGS_THREADS", "off")
    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    assert configure_process() is None and "GOMP_SPINCOUNT" not in os.environ


def test_parallel_map_keeps_the_order_on_several_threads(monkeypatch):
    import threading
    import time

    from kgs_core.progress import listen
    from kgs_core.threads import parallel_map

    monkeypatch.setenv("KGS_THREADS", "2")
    threads, heard = set(), []

    def slow_square(x):
        threads.add(threading.get_ident())
        time.sleep(0.01 * (x % 3))  # later items may finish first
        return x * x

    with listen(lambda stage, done, total: heard.append((stage, done, total))):
        assert parallel_map(slow_square, list(range(12)), desc="squares") == [x * x for x in range(12)]
    assert len(threads) == 2
    assert heard[-1] == ("squares", 12, 12)
    heard.clear()
    with listen(lambda *a: heard.append(a)):
        assert parallel_map(slow_square, [3]) == [9] and parallel_map(slow_square, []) == []
    assert heard == []  # no name, no bar and nothing announced


def test_a_fresh_process_gets_the_placement_and_explicit_settings_win():
    """What libgomp will read: the entry points (`kgs-app`, the job worker) call this before
    torch is imported."""
    code = (
        "import os; from kgs_core.threads import configure_process; configure_process(); import torch; "
        "print(os.environ['OMP_NUM_THREADS'], os.environ['GOMP_SPINCOUNT'], torch.get_num_threads())"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "GOMP_SPINCOUNT", "KGS_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env={**env, "KGS_THREADS": "1"})
    assert out.stdout.split() == ["1", str(SPIN_COUNT), "1"]
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env={**env, "KGS_THREADS": "1", "GOMP_SPINCOUNT": "5"}
    )
    assert out.stdout.split() == ["1", "5", "1"]
    # An OMP_NUM_THREADS of the user's is kept, and no tuner changes it.
    code2 = (
        "import os; from kgs_core.threads import configure_process, tuner_for_process; configure_process(); "
        "print(os.environ['OMP_NUM_THREADS'], tuner_for_process())"
    )
    env2 = {k: v for k, v in env.items() if k != "KGS_OMP_FROM_USER"}
    out = subprocess.run([sys.executable, "-c", code2], capture_output=True, text=True, check=True, env={**env2, "OMP_NUM_THREADS": "1"})
    assert out.stdout.split() == ["1", "None"]


def test_the_job_runner_divides_the_cores(monkeypatch):
    from kgs_backend.jobs import JobRunner

    monkeypatch.setenv("KGS_THREADS", "4")
    assert [JobRunner.share(n) for n in (1, 2, 3, 8)] == [4, 2, 1, 1]
    monkeypatch.setenv("KGS_THREADS", "off")
    assert JobRunner.share(1) is None


def test_the_thread_tuner_follows_what_the_other_processes_use():
    """Fake clocks: per half-second window, the machine's busy CPU seconds and ours."""
    import torch

    from kgs_core.threads import ThreadTuner

    t = {"wall": 0.0, "busy": 0.0, "own": 0.0}
    before = torch.get_num_threads()
    try:
        tuner = ThreadTuner(2, window_s=0.5, machine_busy=lambda: t["busy"], own_cpu=lambda: t["own"], clock=lambda: t["wall"])
        assert tuner.current == 2 and torch.get_num_threads() == 2

        def window(ours: float, others: float) -> None:  # cores used during the next 0.5 s
            t["wall"] += 0.5
            t["own"] += 0.5 * ours
            t["busy"] += 0.5 * (ours + others)
            tuner.observe()

        window(2.0, 0.05)  # alone (the odd daemon)
        assert tuner.current == 2
        window(1.0, 1.0)  # another training took a core
        assert tuner.current == 1 and torch.get_num_threads() == 1 and tuner.others == 1.0
        window(1.0, 1.0)
        assert tuner.current == 1 and tuner.changes == 1  # settled
        t["wall"] += 0.2
        tuner.observe()  # inside a window: nothing measured yet
        assert tuner.current == 1
        window(1.0, 0.0)  # it ended
        assert tuner.current == 2 and torch.get_num_threads() == 2
        window(2.0, 3.0)  # a bigger load than the machine: still one thread
        assert tuner.current == 1
        broken = ThreadTuner(2, machine_busy=lambda: None, clock=lambda: t["wall"])
        t["wall"] += 1.0
        broken.observe()  # no /proc/stat: the count stays
        assert broken.current == 2
    finally:
        torch.set_num_threads(before)


def test_machine_busy_seconds_grows_with_work():
    from kgs_core.threads import machine_busy_seconds

    a = machine_busy_seconds()
    if a is None:
        pytest.skip("no /proc/stat")
    sum(i * i for i in range(3_000_000))
    assert machine_busy_seconds() > a
