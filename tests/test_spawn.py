"""Spawning dynamic Gaussians where a training frame stays unexplained (train/spawn.py), and the
lifespan that keeps them to the time they were made for."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_model import moving_model

from kgs_core.model.dynamic import KinematicsGS
from kgs_core.model.neighbours import neighbour_mean_matrices
from kgs_core.render import intrinsics, look_at
from kgs_core.train.densify import DensifyStrategy
from kgs_core.train.flow import project
from kgs_core.train.spawn import IN_FRONT, NextFrame, Spawned, independent_motion, spawn_unexplained, unexplained_pixels

W = H = 64


def scene_model() -> tuple[KinematicsGS, torch.Tensor, torch.Tensor]:
    """A moving model of 400 Gaussians in front of a camera looking down +z."""
    m = moving_model(n=400, seed=1)
    return m, look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0)), intrinsics(W, H)


def test_unexplained_pixels_are_regions_not_edges():
    image = torch.zeros(H, W, 3)
    target = image.clone()
    target[10:20, 30:42] = 0.8  # a missing object
    target[40, :] = 1.0  # a one-pixel edge off by a pixel
    target[50:52, 5:8] = 0.8  # too small to be worth Gaussians
    mask = unexplained_pixels(image, target)
    assert mask[10:20, 30:42].all()
    assert mask.sum() == 10 * 12
    assert not unexplained_pixels(image, image + 0.1).any()  # under the threshold


def test_independent_motion_is_flow_the_still_scene_does_not_make():
    """A wall at depth 2 seen by a camera that moves sideways: its flow is the parallax, and only
    a patch whose flow differs from that is moving on its own; pixels without flow or without
    anything drawn are not."""
    K = intrinsics(W, H)
    view0 = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0))
    view1 = look_at((0.05, 0.0, -2.0), (0.05, 0.0, 0.0))
    depth = torch.full((H, W, 1), 2.0)
    parallax = -0.05 * float(K[0, 0]) / 2.0  # px: the camera moves +x, the wall moves -x on screen
    flow = torch.zeros(H, W, 2)
    flow[..., 0] = parallax
    assert not independent_motion(depth, view0, K, view1, K, flow).any()
    flow[10:20, 10:20, 1] += 3.0  # something moving down by 3 px
    flow[40:44, 40:44] = float("nan")  # unreliable flow
    depth[50:, :] = 0.0  # nothing drawn
    moving = independent_motion(depth, view0, K, view1, K, flow)
    assert moving[10:20, 10:20].all() and moving.sum() == 100


def test_the_relative_test_reads_a_depth_error_under_a_pan_as_still():
    """The decompositions' reading (`relative`): a camera panning fast past a wall rendered 20 %
    too near gives every pixel 20 % more predicted parallax than the flow shows, several pixels,
    which the absolute test calls motion everywhere; the relative test calls it still, but still
    sees a patch that moves on its own by more than half the parallax, and reads nothing whose
    still motion leaves the next frame."""
    K = intrinsics(W, H)
    view0 = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0))
    view1 = look_at((0.2, 0.0, -2.0), (0.2, 0.0, 0.0))
    true_parallax = -0.2 * float(K[0, 0]) / 2.0
    depth = torch.full((H, W, 1), 2.0 / 1.2)  # rendered too near: predicted parallax 1.2x
    flow = torch.zeros(H, W, 2)
    flow[..., 0] = true_parallax
    assert abs(0.2 * true_parallax) > 1.0  # the depth error is over a pixel ...
    assert independent_motion(depth, view0, K, view1, K, flow).mean() > 0.9  # ... so absolute: all moving
    assert not independent_motion(depth, view0, K, view1, K, flow, relative=0.5).any()
    flow[20:30, 30:40, 1] += abs(true_parallax)  # a patch moving down, as fast as the pan
    moving = independent_motion(depth, view0, K, view1, K, flow, relative=0.5)
    assert moving[20:30, 30:40].all() and moving.sum() == 100
    flow[20:30, :5, 1] += abs(true_parallax)  # on the left edge, where the pan takes pixels out of view
    assert independent_motion(depth, view0, K, view1, K, flow, relative=0.5)[20:30, :5].sum() == 0


def test_spawned_gaussians_land_on_their_pixels_at_their_time_and_fade_away_from_it():
    m, viewmat, K = scene_model()
    t, life = 0.5, 0.05
    strategy = DensifyStrategy()
    strategy.reset(len(m))
    opt = torch.optim.Adam([{"params": [v], "name": k} for k, v in m.params.items()], lr=1e-3)
    with torch.no_grad():
        g = m.at(t, velocity=False)
    target = torch.zeros(H, W, 3)
    target[20:36, 24:40] = torch.tensor([1.0, 0.2, 0.1])
    depth = torch.full((H, W, 1), 3.0)
    n0 = len(m)
    added = spawn_unexplained(
        m,
        opt,
        strategy.state,
        t,
        viewmat,
        K,
        torch.zeros(H, W, 3),
        depth,
        target,
        g.means,
        max_new=50,
        life=life,
        rng=np.random.default_rng(0),
    )
    assert added.gaussians == 50 and len(m) == n0 + 50
    # Every per-Gaussian tensor grew in lock-step; the new ones are dynamic, coloured from the frame.
    assert len(m.dynamic) == len(m.K) == len(m.lifespan) == len(m.own_velocity) == len(strategy.state["grad_sum"]) == len(m)
    assert m.dynamic[n0:].all()
    assert torch.allclose(m.lifespan[n0:], torch.tensor([t, life]).expand(50, 2))
    assert torch.isinf(m.lifespan[:n0, 1]).all()
    rgb = 0.5 + 0.28209479177387814 * m.params.sh0.detach()[n0:, 0]
    assert torch.allclose(rgb, torch.tensor([1.0, 0.2, 0.1]).expand(50, 3), atol=1e-5)
    # At t they land on the unexplained square (within a pixel: the field differs a little
    # between a new Gaussian and its parent), in front of the background.
    with torch.no_grad():
        g = m.at(t, velocity=False)
    uv, z = project(g.means[n0:], viewmat, K)
    assert (uv[:, 0] > 23).all() and (uv[:, 0] < 40).all() and (uv[:, 1] > 19).all() and (uv[:, 1] < 36).all()
    assert (z < 3.0).all()
    # Present at their time, gone three widths away; the others are untouched.
    assert torch.allclose(g.opacities[n0:], m.params.opacities.detach()[n0:])
    far = m.at(t + 3 * life, velocity=False).opacities.detach()
    assert (far[n0:] < 0.012 * m.params.opacities.detach()[n0:]).all()
    assert torch.equal(far[:n0], m.params.opacities.detach()[:n0])


def test_a_spawned_gaussian_joins_a_parent_that_moves_like_its_pixel_not_the_nearest_one():
    """Every Gaussian is "dynamic" (as on real footage, where K flags most of the background),
    but only a group far from the unexplained patch moves as the flow there does; the rest stand
    still. The new Gaussians copy that group, not the still Gaussians beside them, whose
    neighbourhood of the field they would otherwise bend. With no Gaussian moving so, the patch
    gets Gaussians without a parent where they move on their own line (the default), just in
    front of the rendered depth and moving as the flow says, and none where the field would
    carry them."""
    m, viewmat, K = scene_model()
    t = 0.5
    with torch.no_grad():
        m.params.features.copy_(torch.randn(m.params.features.shape, generator=torch.Generator().manual_seed(3)))
        g = m.at(t, velocity=False)
    uv, z = project(g.means.detach(), viewmat, K)
    movers = torch.nonzero((uv[:, 0] > 50) & (uv[:, 0] < 63) & (uv[:, 1] < 63)).squeeze(1)
    assert len(movers) >= 5
    target = torch.zeros(H, W, 3)
    target[22:34, 22:34] = 1.0  # the patch: the still Gaussians are the ones nearest it on screen
    flow = torch.zeros(H, W, 2)
    flow[18:38, 18:38, 1] = 3.0  # it moves 3 px down to the next frame (same camera)
    depth = torch.full((H, W, 1), 5.0)

    def spawn(model, moved):
        at_next = g.means.detach().clone()
        at_next[moved, 1] += 3.0 * z[moved] / float(K[1, 1])  # 3 px down
        return spawn_unexplained(
            model,
            None,
            {},
            t,
            viewmat,
            K,
            torch.zeros(H, W, 3),
            depth,
            target,
            g.means.detach(),
            40,
            0.05,
            np.random.default_rng(0),
            NextFrame(viewmat, K, flow, at_next, t + 0.1),
        )

    n0 = len(m)
    assert spawn(m, movers) == Spawned(36, 0)  # one per 2x2 pixels of the 12x12 patch, each with a parent
    new_features = m.params.features.detach()[n0:]
    parent_of = torch.cdist(new_features, m.params.features.detach()[:n0]).argmin(1)
    assert torch.isin(parent_of, movers).all()
    # No Gaussian moves like the patch: under "own" it gets Gaussians anyway, at the render's
    # depth (5) times IN_FRONT, each moving 3 px down by the next frame as the flow does ...
    m2, _, _ = scene_model()
    assert spawn(m2, torch.zeros(0, dtype=torch.long)) == Spawned(36, 36)
    with torch.no_grad():
        (uv0, z0), (uv1, _) = (project(m2.at(time, velocity=False).means[n0:], viewmat, K) for time in (t, t + 0.1))
    assert torch.allclose(z0, torch.full_like(z0, IN_FRONT * 5.0), atol=1e-4)
    assert (uv0 >= 21).all() and (uv0 <= 34).all()
    assert torch.allclose(uv1 - uv0, torch.tensor([0.0, 3.0]).expand_as(uv0), atol=1e-3)
    # ... and none under "field", where nothing would carry them.
    m3, _, _ = scene_model()
    m3.config.spawned_motion = "field"
    assert spawn(m3, torch.zeros(0, dtype=torch.long)) == Spawned(0, 0) and len(m3) == n0


def test_spawned_gaussians_move_as_the_flow_at_their_pixel_says_whatever_the_field_learns():
    """Under `spawned_motion="own"` (the default) a new Gaussian sits on its pixel at its frame's
    time and reaches, at the next frame's, the pixel the flow moves it to (the same camera here,
    3 px down over 0.1 of the clip), at its depth; the field's later changes do not move it."""
    m, viewmat, K = scene_model()
    t, t_next = 0.5, 0.6
    with torch.no_grad():
        g = m.at(t, velocity=False)
    uv, z = project(g.means, viewmat, K)
    assert ((uv[:, 0] > 30) & (uv[:, 0] < 50) & (uv[:, 1] > 10) & (uv[:, 1] < 50)).sum() >= 5
    target = torch.zeros(H, W, 3)
    target[22:34, 32:44] = 1.0
    flow = torch.zeros(H, W, 2)
    flow[18:38, 28:48, 1] = 3.0
    at_next = g.means.clone()
    at_next[:, 1] += 3.0 * z / float(K[1, 1])  # every Gaussian moves 3 px down: all match
    n0 = len(m)
    added = spawn_unexplained(
        m,
        None,
        {},
        t,
        viewmat,
        K,
        torch.zeros(H, W, 3),
        torch.full((H, W, 1), 5.0),
        target,
        g.means,
        36,
        0.05,
        np.random.default_rng(0),
        NextFrame(viewmat, K, flow, at_next, t_next),
    )
    assert added.gaussians > 20
    new = torch.arange(n0, len(m))

    def pixels(time):
        with torch.no_grad():
            return project(m.at(time, velocity=False).means[new], viewmat, K)

    (uv0, z0), (uv1, z1) = pixels(t), pixels(t_next)
    assert (uv0[:, 0] > 31).all() and (uv0[:, 0] < 44).all() and (uv0[:, 1] > 21).all() and (uv0[:, 1] < 34).all()
    assert torch.allclose(uv1 - uv0, torch.tensor([0.0, 3.0]).expand_as(uv0), atol=1e-3)
    assert torch.allclose(z1, z0, atol=1e-4)
    with torch.no_grad():  # the field learns something else: they stay on their line
        for grid in m.deform.planes.grids:
            grid.add_(0.5)
    assert torch.allclose(pixels(t_next)[0], uv1, atol=1e-4)
    # A saved model keeps the motion; one saved before it existed follows the field, as it trained.
    loaded = KinematicsGS.from_state(m.state())
    assert torch.equal(loaded.own_velocity, m.own_velocity) and loaded.config.spawned_motion == "own"
    old = m.state()
    del old["own_velocity"], old["config"]["spawned_motion"], old["config"]["config_version"]
    assert KinematicsGS.from_state(old).config.spawned_motion == "field"


@pytest.mark.parametrize("motion", ["own", "field"])
@pytest.mark.parametrize("coarse_to_fine", [True, False])
def test_spawned_gaussians_do_not_train_the_field(coarse_to_fine, motion):
    """A Gaussian present for part of the clip moves as `spawned_motion` says: by the field like
    any dynamic one ("field") or by its own velocity ("own"); either way its loss reaches only
    its own parameters: the field and the fine residual learn from the Gaussians present at
    every time alone."""
    m = moving_model(n=60, seed=2, coarse_to_fine=coarse_to_fine, spawned_motion=motion)
    m.lifespan[:20] = torch.tensor([0.4, 0.05])
    m.own_velocity[:20] = torch.tensor([0.1, -0.2, 0.05])
    networks = [p for p in m.parameters() if p.requires_grad]

    def grads(rows):
        m.zero_grad(set_to_none=True)
        m.params.means.grad = None
        g = m.at(0.4, exposure=0.5)
        idx, v = g.extras["dynamic_velocity"]  # (every Gaussian is dynamic here: idx is 0..N-1)
        assert torch.equal(idx, torch.arange(len(m)))
        (g.means[rows].square().sum() + g.covars6[rows].sum() + v[rows].square().sum()).backward()
        field = sum(float(p.grad.abs().sum()) for p in networks if p.grad is not None)
        return field, m.params.means.grad[rows].abs().sum(-1)

    with torch.no_grad():
        g, later = m.at(0.4), m.at(0.5)
    if motion == "field":
        assert (g.means[:20] - m.params.means[:20]).norm(dim=-1).min() > 1e-4  # the field moves them
    else:  # at their centre on their mean; a tenth of the clip later moved by a tenth of their velocity
        assert torch.allclose(g.means[:20], m.params.means[:20])
        assert torch.allclose(later.means[:20] - g.means[:20], 0.1 * m.own_velocity[:20], atol=1e-6)
    field, own = grads(slice(0, 20))
    assert field == 0.0 and (own > 0).all()
    field, own = grads(slice(20, 60))
    assert field > 0.0 and (own > 0).all()


def test_the_field_is_neither_evaluated_for_gaussians_on_their_own_line_nor_averaged_over_them():
    """Under "own" a spawned Gaussian's field offsets are never read: the field is evaluated
    for the others only, and C.F. averages each other Gaussian over its neighbours that are not
    spawned, so moving the spawned ones changes nobody else's offsets."""
    m = moving_model(n=60, seed=3, coarse_to_fine=True, spawned_motion="own")
    m.lifespan[:20] = torch.tensor([0.4, 0.05])
    idx = torch.arange(len(m))
    knn = m.knn_index()
    assert (knn[20:] < 20).any()  # others have spawned neighbours in their rows
    rows_seen = []
    at_times = m.deform.at_times
    m.deform.at_times = lambda x, tt: rows_seen.append(len(x)) or at_times(x, tt)
    with torch.no_grad():
        before = m.offsets_at(idx, [0.3, 0.45])
        m.params.means[:20] += 0.3
        after = m.offsets_at(idx, [0.3, 0.45])
    assert rows_seen == [40, 40]
    for b, a in zip(before, after):
        assert b.dx[20:].abs().max() > 1e-3  # the field moves the others
        assert torch.equal(b.cat()[20:], a.cat()[20:])
    # Each other Gaussian's coarse offset is the mean over its neighbours that are not spawned.
    raw = at_times(m.params.means[20:].detach(), [torch.full((40,), 0.3)])[0].cat()
    coarse = m.neighbour_mean(torch.cat([torch.zeros(20, 9), raw]))[20:]
    i = int(torch.nonzero((knn[20:] < 20).any(1))[0]) + 20
    kept = knn[i][knn[i] >= 20]
    assert torch.allclose(coarse[i - 20], raw[kept - 20].mean(0), atol=1e-6)


def test_a_neighbour_mean_without_the_dropped_rows_renormalises_and_falls_back_to_itself():
    knn = torch.tensor([[0, 1, 2], [1, 2, 2], [2, 1, 0]])
    x = torch.tensor([[1.0], [10.0], [100.0]])
    w, wt = neighbour_mean_matrices(knn)
    assert torch.allclose(w @ x, torch.tensor([[37.0], [70.0], [37.0]]))
    w, wt = neighbour_mean_matrices(knn, drop=torch.tensor([False, True, True]))
    # row 0 keeps itself; row 1 has nobody left and takes itself; row 2 keeps only 0
    assert torch.allclose(w @ x, torch.tensor([[1.0], [10.0], [1.0]]))
    assert torch.allclose(wt.to_dense(), w.to_dense().T)


def test_a_frame_the_render_explains_gets_nothing():
    m, viewmat, K = scene_model()
    with torch.no_grad():
        g = m.at(0.3, velocity=False)
    image = torch.rand(H, W, 3)
    n0 = len(m)
    assert (
        spawn_unexplained(
            m, None, {}, 0.3, viewmat, K, image, torch.ones(H, W, 1), image, g.means, 50, 0.05, np.random.default_rng(0)
        ).gaussians
        == 0
    )
    assert len(m) == n0


def test_lifespans_survive_pruning_the_split_and_a_save():
    m, viewmat, K = scene_model()
    with torch.no_grad():
        g = m.at(0.5, velocity=False)
    target = torch.zeros(H, W, 3)
    target[20:36, 24:40] = 1.0
    spawn_unexplained(
        m, None, {}, 0.5, viewmat, K, torch.zeros(H, W, 3), torch.full((H, W, 1), 3.0), target, g.means, 20, 0.05, np.random.default_rng(0)
    )
    bounded = m.lifespan[:, 1].isfinite()
    # A decomposition with a τ above every K keeps the ones present for part of the clip dynamic.
    m.decompose(tau=1e9)
    assert torch.equal(m.dynamic, bounded)
    m.own_velocity[bounded] = torch.randn(int(bounded.sum()), 3)
    velocity = m.own_velocity.clone()
    keep = torch.arange(len(m)) % 2 == 0
    m.keep_gaussians(keep)
    assert torch.equal(m.lifespan[:, 1].isfinite(), bounded[keep]) and torch.equal(m.own_velocity, velocity[keep])
    loaded = KinematicsGS.from_state(m.state())
    assert torch.equal(loaded.lifespan, m.lifespan) and torch.equal(loaded.own_velocity, m.own_velocity)
    bad = m.state()
    bad["own_velocity"][0, 1] = float("nan")
    with pytest.raises(ValueError, match="own_velocity"):
        KinematicsGS.from_state(bad)
    # A state saved before lifespans existed loads with every Gaussian present at every time.
    old = m.state()
    del old["lifespan"]
    assert torch.isinf(KinematicsGS.from_state(old).lifespan[:, 1]).all()
    for broken in (
        lambda x: x[:-1],
        lambda x: x[:, :1],
        lambda x: x.index_fill(1, torch.tensor([1]), float("nan")),
        lambda x: x.index_fill(1, torch.tensor([1]), 0.0),
        lambda x: x.index_fill(1, torch.tensor([0]), float("inf")),
    ):
        bad = m.state()
        bad["lifespan"] = broken(bad["lifespan"])
        with pytest.raises(ValueError, match="lifespan"):
            KinematicsGS.from_state(bad)


def test_trainer_spawns_only_in_frames_with_a_flow_to_the_next(tmp_path, monkeypatch):
    """Spawning's motion gate needs the flow to the next frame of the camera: a camera's last
    frame, however badly it fits, gets no Gaussians; the worst of the others does, with its
    next frame's flow."""
    import kgs_core.train.events as events_module
    import kgs_core.train.trainer as trainer_module
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.train.config import make_config

    scene = load_scene(
        synthesize("sheet", tmp_path / "s", blur="mild", size=40, frames=6, subframes=2, seed=0, progress=False, overwrite=True)
    )
    cfg = make_config("fast", iterations=10)
    cfg.spawn_frames = 2
    tr = trainer_module.Trainer(scene, tmp_path / "r", cfg, progress=False)
    tr.init_model()
    tr.model.decompose(tau=-1.0, recompute=False)
    calls = []
    monkeypatch.setattr(events_module, "spawn_unexplained", lambda *args: calls.append((args[3], args[-1])) or Spawned(7, 2))
    tr.frame_loss = torch.tensor([0.01, 0.01, 0.5, 0.01, 0.01, 1.0])  # the last frame fits worst
    tr.spawn(100)
    frames = scene.train_frames
    assert [t for t, _ in calls] == [frames[2].time]
    nxt = calls[0][1]
    assert nxt.flow is tr.flows[frames[2].id][1] and nxt.means.shape == (len(tr.model), 3)
    # run.json's record: one attempt, at that frame's time, 7 Gaussians (what spawn_unexplained said).
    tr.spawn(200)
    assert tr.spawn_summary() == {
        "attempts": 2,
        "gaussians": 14,
        "frames": 1,
        "by_time": {f"{frames[2].time:.4f}": 14},
        "without_parent": 4,
    }
