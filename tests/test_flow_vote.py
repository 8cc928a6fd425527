"""The decompositions' reading of the optical flow (train/flow_vote.py): what moves on its own,
where K sees no motion, becomes dynamic."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from test_model import moving_model

from kgs_core.data.scene import Camera, Frame
from kgs_core.model.render import camera_tensors
from kgs_core.render import intrinsics, look_at
from kgs_core.train.flow import frame_flows, project
from kgs_core.train.flow_vote import MIN_GAUSSIANS, flow_moving, read_frames

W = H = 64
PATCH = (slice(20, 44), slice(20, 44))  # rows, columns of the pixels that move on their own


def still_clip(n_frames: int = 4):
    """A cloud of 600 static Gaussians seen by a still camera over `n_frames` frames, and flows
    between consecutive frames that are zero but in PATCH, which moves 3 px down."""
    m = moving_model(n=600, seed=2)
    m.dynamic[:] = False  # canonical positions at every time: the same pixels in every frame
    cam = Camera(intrinsics(W, H).numpy(), look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0)).numpy(), W, H)
    frames = [Frame(id=f"f{i}", image_path=Path(f"f{i}.png"), time=i / (n_frames - 1), camera=cam) for i in range(n_frames)]
    flow = torch.zeros(H, W, 2)
    flow[PATCH[0], PATCH[1], 1] = 3.0
    flows = {f.id: (i + 1, flow) for i, f in enumerate(frames[:-1])}
    return m, frames, flows


def in_patch(m, frame) -> torch.Tensor:
    """(N,) bool: Gaussians whose centre projects into PATCH."""
    uv, _ = project(m.params.means.detach(), *camera_tensors(frame.camera))
    u, v = uv[:, 0].round(), uv[:, 1].round()
    return (u >= PATCH[1].start) & (u < PATCH[1].stop) & (v >= PATCH[0].start) & (v < PATCH[0].stop)


def test_gaussians_on_pixels_moving_on_their_own_become_dynamic():
    m, frames, flows = still_clip()
    none = torch.zeros(len(m), dtype=torch.bool)
    moving = flow_moving(m, frames, flows, none, share=0.1, exposure=0.0, dt=1.0)
    assert moving.sum() >= MIN_GAUSSIANS
    assert not (moving & ~in_patch(m, frames[0])).any()  # only where the flow moves
    assert moving.sum() < in_patch(m, frames[0]).sum()  # not the ones hidden behind the front ones


def test_nothing_is_read_where_k_already_covers_the_motion_nothing_moves_or_no_flow_holds():
    m, frames, flows = still_clip()
    every = torch.ones(len(m), dtype=torch.bool)
    assert not flow_moving(m, frames, flows, every, share=0.1, exposure=0.0, dt=1.0).any()
    still = {k: (j, torch.zeros(H, W, 2)) for k, (j, _) in flows.items()}
    none = torch.zeros(len(m), dtype=torch.bool)
    assert not flow_moving(m, frames, still, none, share=0.1, exposure=0.0, dt=1.0).any()
    rejected = {k: (j, torch.full((H, W, 2), float("nan"))) for k, (j, _) in flows.items()}  # forward-backward failed
    assert not flow_moving(m, frames, rejected, none, share=0.1, exposure=0.0, dt=1.0).any()


def test_scattered_moving_pixels_are_not_an_object():
    """Moving pixels in strips 2 px wide, two rows in three over the whole patch (a hand-held
    pan's depth errors look so, not an object), are opened away (spawn.large_regions)."""
    m, frames, flows = still_clip()
    strips = torch.zeros(H, W, 2)
    for r in range(PATCH[0].start, PATCH[0].stop, 3):
        strips[r : r + 2, PATCH[1], 1] = 3.0
    flows = {k: (j, strips) for k, (j, _) in flows.items()}
    none = torch.zeros(len(m), dtype=torch.bool)
    assert not flow_moving(m, frames, flows, none, share=0.1, exposure=0.0, dt=1.0).any()


def test_the_reading_reads_at_most_its_views_and_never_a_cameras_last_frame():
    """`read_frames`: two cameras of 40 frames each, read 16 of the 78 with a next frame, spread
    over both; the flows the decomposition computes for a run without them are those 16 alone."""
    cam = still_clip()[1][0].camera
    frames = [Frame(id=f"c{c}f{i}", image_path=Path("x.png"), time=i / 39, camera=cam, camera_id=c) for c in (0, 1) for i in range(40)]
    read = read_frames(frames, 16)
    assert len(read) == 16 and {f.camera_id for f in read} == {0, 1}
    assert all(f.time < 1.0 for f in read)
    assert read_frames(frames[:1], 16) == []  # one frame: nothing to read


def test_without_opencv_the_flow_says_what_to_install_or_turn_off(monkeypatch):
    """OpenCV is a dependency, but a hand-made environment may lack it: the flows the decompositions
    read then fail with what to install and which settings do without them."""
    monkeypatch.setitem(sys.modules, "cv2", None)  # makes `import cv2` raise ImportError
    _, frames, _ = still_clip()
    with pytest.raises(RuntimeError, match="opencv-python-headless.*flow_vote_share=0"):
        frame_flows(frames)
