"""Serving benchmark: `kgs-app bench serve`.

1. Time change → dynamic buffer, in process: exact deformation-field evaluation against the
   trajectory cache (interpolation), for N Gaussians with a given dynamic share; and the
   interpolation error against exact evaluation.
2. Many scrubbing clients: a real `uvicorn` server on loopback, C WebSocket clients each
   scrubbing (send a time, wait for its buffer, repeat) for S seconds; p50/p95 latency.

The model is synthetic (random Gaussians, an untrained fast-preset deformation field): the
cost of evaluating it does not depend on what it learned.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import statistics
import struct
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import torch

from .machine import machine


def make_run(root: Path, n: int, dynamic_share: float, seed: int = 0) -> Path:
    from kgs_core.model.dynamic import KinematicsGS
    from kgs_core.model.gaussians import init_from_points
    from kgs_core.run import save_torch, write_run_json
    from kgs_core.train.config import make_config

    rng = np.random.default_rng(seed)
    cfg = make_config("fast")
    pts = rng.uniform(-1, 1, size=(n, 3))
    params = init_from_points(pts, rng.uniform(0, 1, size=(n, 3)), cfg.model.sh_degree, cfg.model.feature_dim, seed=seed)
    model = KinematicsGS(params, cfg.model)
    K = torch.from_numpy(rng.uniform(0, 1, n).astype(np.float32)) * 2 * cfg.model.tau
    cut = torch.quantile(K, 1 - dynamic_share)
    model.K = K * (cfg.model.tau / float(cut))
    model.decompose(recompute=False)
    run = root / f"synthetic-{n}"
    run.mkdir(parents=True, exist_ok=True)
    save_torch(run / "model.pt", {"model": model.state(), "levels": []})
    write_run_json(run, {"status": "done", "scene": str(root / "no-scene"), "config": cfg.to_dict(), "dt": 1 / 60, "exposure": 0.5})
    return run


def bench_in_process(run: Path, repeats: int) -> dict:
    from kgs_core.run_view import RunView
    from kgs_core.splat_buffer import unpack_buffer

    view = RunView(run)
    view.dynamic_buffer(0.5, exact=True)  # warm-up (kNN, allocations)
    ts = np.random.default_rng(1).uniform(0, 1, repeats)
    t0 = time.perf_counter()
    exact = [view.dynamic_buffer(float(t), exact=True) for t in ts]
    exact_ms = (time.perf_counter() - t0) / repeats * 1e3
    t0 = time.perf_counter()
    view.trajectories(view.run.n_levels, 0.0)
    tr = view._trajectories[(view.run.n_levels, view.version, 0.0)]
    tr.ready.wait()
    view.dynamic_buffer(0.5)  # the cache's first answer cuts it to the kept Gaussians
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    interp = [view.dynamic_buffer(float(t)) for t in ts]
    interp_ms = (time.perf_counter() - t0) / repeats * 1e3
    errs = []
    for a, b in zip(exact, interp):
        ha, ra, _ = unpack_buffer(a)
        hb, rb, _ = unpack_buffer(b)
        assert hb["interpolated"] and not ha["interpolated"]
        errs.append(np.linalg.norm(ra["position"] - rb["position"], axis=1))
    e = np.concatenate(errs)
    h, rec, _ = unpack_buffer(exact[0])
    return {
        "dynamic": h["count"],
        "exact_ms": exact_ms,
        "interpolated_ms": interp_ms,
        "cache_build_s": build_s,
        "cache_samples": len(tr.times),
        "cache_mb": tr.nbytes() / 2**20,
        "interp_err_rms": float(np.sqrt((e**2).mean())),
        "interp_err_max": float(e.max()),
        "buffer_bytes": len(exact[0]),
    }


def load_run_means(run: Path) -> np.ndarray:
    from kgs_core.run import load_run

    return load_run(run).model.params.means.detach().numpy()


async def scrub_client(url: str, seconds: float, lat: list, seed: int) -> None:
    import websockets

    rnd = random.Random(seed)
    async with websockets.connect(url, max_size=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "subscribe"}))
        while True:  # the static set
            m = await ws.recv()
            if isinstance(m, bytes):
                break
        t, end, seq = rnd.random(), time.perf_counter() + seconds, 0
        while time.perf_counter() < end:
            t = min(1.0, max(0.0, t + rnd.uniform(-0.05, 0.05)))
            seq += 1
            t0 = time.perf_counter()
            await ws.send(json.dumps({"type": "time", "t": t, "seq": seq}))
            while True:
                m = await ws.recv()
                if isinstance(m, bytes):
                    lat.append((time.perf_counter() - t0) * 1e3)
                    break


async def wait_for_cache(url: str, timeout: float = 300.0) -> float:
    """Scrubs slowly until the server answers from its trajectory cache; returns the seconds."""
    import websockets

    t0 = time.perf_counter()
    async with websockets.connect(url, max_size=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "subscribe"}))
        while time.perf_counter() - t0 < timeout:
            await ws.send(json.dumps({"type": "time", "t": 0.5}))
            while True:
                m = await ws.recv()
                if isinstance(m, bytes):
                    (h,) = struct.unpack_from("<I", m, 4)
                    header = json.loads(m[8 : 8 + h])
                    break
            if header.get("interpolated"):
                return time.perf_counter() - t0
            await asyncio.sleep(1.0)
    raise RuntimeError("the trajectory cache was not ready in time")


async def clients(url: str, n: int, seconds: float) -> tuple[list[float], int]:
    """Latencies of `n` scrubbing clients, and how many of them failed."""
    lat: list[float] = []
    done = await asyncio.gather(*(scrub_client(url, seconds, lat, i) for i in range(n)), return_exceptions=True)
    return lat, sum(isinstance(d, BaseException) for d in done)


def rss_mb(pid: int) -> float:
    """Resident memory of a process (Linux), MB."""
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return math.nan


def api(base: str, method: str, path: str, body: dict | None = None) -> dict:
    req = urllib.request.Request(
        base + path, method=method, data=None if body is None else json.dumps(body).encode(), headers={"Content-Type": "application/json"}
    )
    return json.loads(urllib.request.urlopen(req).read() or b"null")


def bench_clients(run: Path, n_clients: int, seconds: float, warm_cache: bool, training_scene: Path | None = None) -> dict:
    """`n_clients` scrubbing one run for `seconds`; with `training_scene`, while the server
    trains the fast preset on it (a job started through the API, cancelled afterwards)."""
    from kgs_backend.launch import ServerProcess

    paths = [run] + ([training_scene] if training_scene else [])
    with ServerProcess(paths, Path(tempfile.mkdtemp(prefix="kgs-bench-ws-"))) as srv:
        url = srv.base.replace("http", "ws", 1) + f"/api/runs/{srv.runs[0]['id']}/stream"
        asyncio.run(clients(url, 1, 1.0))  # load the model
        cache_s = asyncio.run(wait_for_cache(url)) if warm_cache else None
        job = None
        if training_scene:
            scene_id = api(srv.base, "GET", "/api/scenes")[0]["id"]
            job = api(srv.base, "POST", "/api/runs", {"scene_id": scene_id, "iterations": 1_000_000})["id"]
            time.sleep(10.0)  # past the job's start-up: scrub while it trains
        rss0 = rss_mb(srv.proc.pid)
        lat, errors = asyncio.run(clients(url, n_clients, seconds))
        rss1 = rss_mb(srv.proc.pid)
        trained = None
        if job:
            row = api(srv.base, "GET", f"/api/runs/{job}")
            trained = (row.get("progress") or {}).get("iteration")
            if row["status"] != "running":
                raise RuntimeError(f"the training job was not running while the clients scrubbed: {row['status']} {row.get('error')}")
            api(srv.base, "POST", f"/api/runs/{job}/cancel")
    lat.sort()
    return {
        "clients": n_clients,
        "seconds": seconds,
        "requests": len(lat),
        "errors": errors,
        "p50_ms": statistics.median(lat),
        "p95_ms": lat[int(0.95 * (len(lat) - 1))],
        "per_client_hz": len(lat) / seconds / n_clients,
        "cache_ready_s": cache_s,
        "server_rss_mb": (rss0, rss1),
        "training_iteration": trained,
    }


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="kgs-app bench serve", description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--dynamic-share", type=float, default=0.2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--skip-clients", action="store_true")
    ap.add_argument(
        "--with-training", action="store_true", help="also scrub (cache warm) while the server trains the demo scene through its API"
    )
    ap.add_argument("--run", help="also measure a real run directory (interpolation error of a trained field)")
    args = ap.parse_args(argv)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    root = Path(tempfile.mkdtemp(prefix="kgs-bench-serve-"))
    run = make_run(root, args.gaussians, args.dynamic_share)
    print(f"# {args.gaussians:,} Gaussians, {args.dynamic_share:.0%} dynamic; {machine()}")
    r = bench_in_process(run, args.repeats)
    print(
        f"time change -> dynamic buffer ({r['dynamic']:,} splats, {r['buffer_bytes'] / 2**20:.2f} MB): "
        f"exact {r['exact_ms']:.1f} ms, interpolated {r['interpolated_ms']:.1f} ms; trajectory cache "
        f"{r['cache_samples']} samples, {r['cache_mb']:.0f} MB, built in {r['cache_build_s']:.1f} s; "
        f"interpolation error RMS {r['interp_err_rms']:.2e}, max {r['interp_err_max']:.2e} (scene units)"
    )
    if args.run:
        r = bench_in_process(Path(args.run), args.repeats)
        extent = float(np.ptp(load_run_means(Path(args.run)), axis=0).max())
        print(
            f"{args.run}: {r['dynamic']:,} dynamic; exact {r['exact_ms']:.1f} ms, interpolated "
            f"{r['interpolated_ms']:.1f} ms; interpolation error RMS {r['interp_err_rms']:.2e}, max "
            f"{r['interp_err_max']:.2e} (scene extent {extent:.2f}); cache {r['cache_samples']} samples, "
            f"built in {r['cache_build_s']:.1f} s"
        )
    if not args.skip_clients:
        cases = [(False, None), (True, None)]
        if args.with_training:
            from kgs_core.data.synth.generate import DEFAULT_SCENE, synthesize

            cases.append((True, synthesize(DEFAULT_SCENE, root / "train-scene", blur="mild", progress=False)))
        for warm, scene in cases:
            c = bench_clients(run, args.clients, args.seconds, warm, scene)
            what = "trajectory cache warm" if warm else "cold start (exact until the cache is built)"
            if scene:
                what += f", while the server trains the fast preset (iteration {c['training_iteration']} at the end)"
            print(
                f"{c['clients']} scrubbing clients, {c['seconds']:.0f} s, {what}: "
                f"{c['requests']} buffers, {c['errors']} errors, p50 {c['p50_ms']:.0f} ms, p95 {c['p95_ms']:.0f} ms, "
                f"{c['per_client_hz']:.1f} buffers/s per client; server RSS {c['server_rss_mb'][0]:.0f} -> "
                f"{c['server_rss_mb'][1]:.0f} MB"
            )
    return 0
