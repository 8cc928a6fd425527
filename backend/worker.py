"""The job process: `python -m kgs_backend.worker KIND SPEC_JSON JOB_ID`.

Every long job (synthesize, ingest, train, export) runs here, in its own process, so that a
crash or a cancel never takes the server down and training survives a client (or server)
restart. Progress goes to files the server polls: training writes `progress.json` in the run
directory (plus the run's own log.csv/run.json), ingest its current stage to the file its spec
names; other jobs only succeed or fail. SIGTERM asks the job to stop: training then saves a
checkpoint and the model as they are, ingest unwinds and leaves nothing ("cancelled").
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import sys
import time
from pathlib import Path

STOP = False


def _on_term(signum, frame) -> None:
    global STOP
    STOP = True


def run_train(spec: dict) -> None:
    from kgs_core.data.formats import load_scene
    from kgs_core.io import atomic_write_text
    from kgs_core.model.decomposition import decomposition_counts
    from kgs_core.threads import omp_threads, tuner_for_process
    from kgs_core.train.config import TrainConfig, make_config
    from kgs_core.train.trainer import Trainer

    run_dir = Path(spec["run_dir"])
    if spec.get("config"):  # a full configuration (fine-tuning builds one from the parent run)
        cfg = TrainConfig.from_dict(spec["config"])
    else:
        overrides = dict(spec.get("overrides") or {})
        cfg = None
    scene = load_scene(spec["scene_dir"])
    if cfg is None:  # the preset fitted to the scene (frames, resolution, scale), overrides winning
        cfg = make_config(spec.get("preset", "fast"), ablate=tuple(spec.get("ablate") or ()), scene=scene, **overrides)
        if spec.get("init_from"):  # the server's own path of a parent run the request named by id
            cfg = dataclasses.replace(cfg, init_from=spec["init_from"])
    t0 = time.time()
    state = {"last": 0.0, "psnr": None}

    def on_log(row: dict) -> None:
        state["psnr"] = row.get("psnr_heldout")

    def on_step(it: int, loss: float) -> None:
        now = time.time()
        if now - state["last"] < 0.5 and it < cfg.iterations:
            return
        state["last"] = now
        counts = decomposition_counts(trainer.model, trainer.static_only)
        atomic_write_text(
            run_dir / "progress.json",
            json.dumps(
                {
                    "iteration": it,
                    "iterations": cfg.iterations,
                    "loss": loss,
                    "psnr_heldout": state["psnr"],
                    "elapsed": now - t0,
                    "gaussians": counts["gaussians"],
                    "dynamic_share": counts["dynamic_share"],
                }
            ),
        )

    # The job runner's share of the cores to start with, then whatever the load leaves free.
    threads = tuner_for_process(start=omp_threads())
    trainer = Trainer(scene, run_dir, cfg, progress=False, on_log=on_log, should_stop=lambda: STOP, on_step=on_step, threads=threads)
    trainer.run(resume=bool(spec.get("resume")))


def run_synth(spec: dict) -> None:
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.job_options import SynthOptions

    o = SynthOptions.model_validate({k: v for k, v in spec.items() if k in SynthOptions.model_fields})
    synthesize(out=spec["out"], progress=False, overwrite=True, **o.model_dump())


class Cancelled(Exception):
    """SIGTERM during a job that has no checkpoint to save: unwind, so that temporary folders go."""


def _raise_cancelled(signum, frame) -> None:
    raise Cancelled("cancelled")


def stage_writer(path: Path, min_interval: float = 0.5):
    """A `kgs_core.progress` listener that keeps `path` (JSON) at the job's current stage: the
    stage, its count and total, the seconds since the start, and the seconds each earlier stage
    took. Written at each new stage and at most every `min_interval` s within one."""
    from kgs_core.io import atomic_write_text

    t0 = time.time()
    state = {"stage": None, "since": t0, "last": 0.0, "done_stages": []}

    def on_progress(stage: str, done: int, total: int | None) -> None:
        now = time.time()
        if stage != state["stage"]:
            if state["stage"] is not None:
                state["done_stages"].append([state["stage"], round(now - state["since"], 2)])
            state["stage"], state["since"] = stage, now
        elif now - state["last"] < min_interval and done != total:
            return
        state["last"] = now
        atomic_write_text(
            path, json.dumps({"stage": stage, "done": done, "total": total, "elapsed": round(now - t0, 2), "stages": state["done_stages"]})
        )

    return on_progress


def run_ingest(spec: dict) -> None:
    from kgs_core.data.ingest import ingest
    from kgs_core.job_options import IngestOptions
    from kgs_core.progress import listen

    # Cancelling (SIGTERM) raises between SfM's steps: ingest writes into temporary folders and
    # renames only a finished scene, so nothing half-made is left.
    asked: list[int] = []

    def cancel(signum, frame) -> None:
        asked.append(signum)
        _raise_cancelled(signum, frame)

    previous = signal.signal(signal.SIGTERM, cancel)
    options = IngestOptions.model_validate({k: v for k, v in spec.items() if k in IngestOptions.model_fields})
    listener = stage_writer(Path(spec["progress"])) if spec.get("progress") else (lambda *a: None)
    try:
        try:
            with listen(listener):
                # no cache: the uploaded video is deleted afterwards, so its frame set would never be reused
                ingest(
                    spec["video"],
                    spec["out"],
                    eval_video=spec.get("eval_video"),
                    cache_dir=False,
                    overwrite=True,
                    **options.ingest_arguments(),
                )
        finally:
            signal.signal(signal.SIGTERM, previous)
        if asked or STOP:
            # The cancel came as the ingest ended, or its exception was lost on the way (raised in
            # a callback from native code that carried on): a cancel still means no scene, and
            # the uploaded videos kept for a retry.
            raise Cancelled("cancelled")
    except Cancelled:
        shutil.rmtree(spec["out"], ignore_errors=True)
        raise
    # The uploaded copies go once their frames are in the scene; after a failure or a cancel they
    # stay, so that the ingest can be retried with other options (deleting the scene removes them).
    for key in ("video", "eval_video"):
        if spec.get("delete_video") and spec.get(key):
            Path(spec[key]).unlink(missing_ok=True)


def run_export(spec: dict) -> None:
    from kgs_core.export import export_run
    from kgs_core.job_options import ExportOptions
    from kgs_core.progress import listen

    o = ExportOptions.model_validate({k: v for k, v in spec.items() if k in ExportOptions.model_fields})
    listener = stage_writer(Path(spec["progress"])) if spec.get("progress") else (lambda *a: None)
    with listen(listener):
        export_run(spec["run_dir"], out=spec["out"], overwrite=True, progress=False, **o.export_arguments())


JOBS = {"train": run_train, "synth": run_synth, "ingest": run_ingest, "export": run_export}


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGTERM, _on_term)
    kind, spec = argv[0], json.loads(argv[1])  # argv[2], the job id, names the process (JobRunner)
    JOBS[kind](spec)
    return 0


if __name__ == "__main__":
    from kgs_core.threads import configure_process

    configure_process()  # the job runner's share (placement_env) is already in the environment
    sys.exit(main(sys.argv[1:]))
