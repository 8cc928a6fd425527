"""Training on a Ray cluster: `--ray [ADDRESS]` of `bench quality`, `bench real` and `train-many`.

Ray is optional (`pip install 'kinematics-gs[cluster]'`): nothing imports it unless `--ray` is
given, and a missing Ray is a clear error. Each training becomes one Ray task that reserves
`task_cpus` CPUs and runs that many threads (kgs_core.threads), so tasks on one node never
oversubscribe it. A task reads its scene from, and writes its run directory to, the paths the
driver names: on a cluster they must lie on storage every node mounts (docs/cluster.md).

`ADDRESS`: empty (plain `--ray`) starts a local Ray on this machine; `auto` joins the cluster
this node belongs to (`ray start --head` / `ray start --address=...`); `ray://HOST:10001`
connects a remote client.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # importing the trainer imports torch: not while the CLI parses its options
    from kgs_core.train.trainer import Trainer


class ClusterError(ValueError):
    pass


def _ray():
    try:
        import ray
    except ImportError:
        raise ClusterError("--ray needs Ray, an optional extra: pip install 'kinematics-gs[cluster]' (or pip install 'ray>=2.9')") from None
    return ray


def connect(address: str | None, num_cpus: int | None = None):
    """Starts (empty address) or joins a Ray instance; returns the `ray` module."""
    ray = _ray()
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)
    return ray


def train_remote(scene_dir: str, run_dir: str, config: dict, cpus: int) -> dict:
    """The body of a Ray task (a plain function, so that it is tested without Ray too)."""
    import torch

    from kgs_core.data.formats import load_scene
    from kgs_core.train.config import TrainConfig
    from kgs_core.train.trainer import Trainer

    from .bench.machine import machine

    torch.set_num_threads(cpus)
    scene = load_scene(scene_dir)
    tr = Trainer(scene, run_dir, TrainConfig.from_dict(config), progress=False)
    info = tr.run()
    return {"info": info, "train_seconds": tr.train_seconds, "node": machine()}


def run_trainers(trainers: list[Trainer], address: str | None, task_cpus: int = 1) -> list[str]:
    """Trains every (not yet started) trainer as a Ray task and fills in what a local run
    would leave on it (`info`, `train_seconds`, `iteration`); their run directories are
    written by the tasks. Returns each task's node description, in order."""
    from tqdm import tqdm

    ray = connect(address)
    task = ray.remote(train_remote).options(num_cpus=task_cpus, runtime_env={"env_vars": _placement(task_cpus)})
    refs = [task.remote(str(Path(t.scene.root).resolve()), str(Path(t.run_dir).resolve()), t.cfg.to_dict(), task_cpus) for t in trainers]
    index = {ref: i for i, ref in enumerate(refs)}
    results: list[dict | None] = [None] * len(refs)
    pending = list(refs)
    with tqdm(total=len(refs), desc=f"ray: {len(refs)} trainings", unit="run") as bar:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                results[index[ref]] = ray.get(ref)
                bar.update(1)
    for t, r in zip(trainers, results):
        t.info, t.train_seconds, t.iteration = r["info"], r["train_seconds"], r["info"]["iteration"]
    return [r["node"] for r in results]


def _placement(cpus: int) -> dict[str, str]:
    from kgs_core.threads import placement_env

    return placement_env(cpus)


def add_ray_options(ap) -> None:
    """`--ray [ADDRESS]` and `--task-cpus N`, as every command that can use Ray spells them."""
    ap.add_argument(
        "--ray",
        nargs="?",
        const="",
        metavar="ADDRESS",
        help="train as Ray tasks: alone, a local Ray on this machine; 'auto' or ray://HOST:PORT, a "
        "cluster (pip install 'kinematics-gs[cluster]'; docs/cluster.md)",
    )
    ap.add_argument("--task-cpus", type=int, default=1, help="CPUs each Ray task reserves and uses (default 1)")


def ray_runner(args, nodes: list[str]) -> dict:
    """`equal_time`'s keyword for parsed `args`: with `--ray`, `train_all` trains as Ray tasks
    (their nodes appended to `nodes`); without, nothing (the local default, and no Ray import)."""
    if args.ray is None:
        return {}
    if args.task_cpus < 1:
        raise ClusterError(f"--task-cpus must be at least 1, got {args.task_cpus}")
    connect(args.ray)
    return {"train_all": lambda trainers: nodes.extend(run_trainers(trainers, args.ray, args.task_cpus))}


def timing_note(nodes: list[str], task_cpus: int) -> str:
    """What the times of a Ray run mean: each configuration's rate comes from its own task."""
    kinds = sorted(set(nodes))
    note = (
        f"times: each configuration's own Ray task ({task_cpus} CPU{'s' if task_cpus > 1 else ''} each, not stepped "
        f"in turn) on {len(kinds)} node kind{'s' if len(kinds) > 1 else ''}: " + "; ".join(kinds)
    )
    if len(kinds) > 1:
        note += (
            " -- WARNING: the equal-time budget compares rates measured on different kinds of node; "
            "pin the sweep to one kind (a Ray custom resource) for a fair budget"
        )
    return note
