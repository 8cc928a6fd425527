"""Posing the frames a keyframe model left out (`register_rest`): absolute-pose RANSAC against the
model's points, through each frame's verified matches, in passes (data/sfm.py, `map_keyframes`)."""

from __future__ import annotations

import numpy as np

from ..progress import progress_bar

MIN_CORRESPONDENCES = 12  # 2D-3D matches needed before a frame is posed by absolute pose


def cam_from_world(im):
    return im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world


def verified_partners(d) -> dict[int, list[int]]:
    """image id -> the images it has a verified two-view geometry with."""
    import pycolmap

    pair_ids, counts = d.read_two_view_geometry_num_inliers()
    partners: dict[int, list[int]] = {}
    for pair_id, count in zip(pair_ids, counts):
        if count > 0:
            a, b = pycolmap.pair_id_to_image_pair(int(pair_id))
            partners.setdefault(a, []).append(b)
            partners.setdefault(b, []).append(a)
    return partners


def register_rest(d, model, images: list, progress: bool) -> tuple[dict, list[int]]:
    """`({name: (camera id, cam_from_world)}, frames posed in each pass)` for the `images` that
    absolute pose can place against `model`'s points, in passes. The first pass uses each image's
    verified matches to the model's images; each later pass also uses its matches to the images
    posed in earlier passes, through the 3D points of their PnP inliers. Sequential matching
    pairs a frame only with the frames a power of two positions away, so with keyframes every 8th
    frame, a frame 3 or 5 frames from both neighbouring keyframes shares no verified pair with
    either, but it does with the frames 1 or 2 away, which the first pass poses."""
    partners = verified_partners(d)
    observed = {}  # (posed image id, keypoint index) -> 3D point id
    for im in model.images.values():
        if im.has_pose:
            for j, p in enumerate(im.points2D):
                if p.has_point3D():
                    observed[(im.image_id, j)] = p.point3D_id
    references = {im.image_id for im in model.images.values() if im.has_pose}
    posed, passes, remaining = {}, [], list(images)
    while remaining:
        found = {}
        desc = "register" if not passes else f"register, pass {len(passes) + 1}"
        for image in progress_bar(remaining, desc=desc, show=progress):
            pose = absolute_pose(d, model, image, [p for p in partners.get(image.image_id, ()) if p in references], observed)
            if pose is not None:
                found[image.name] = (image, *pose)
        if not found:
            break
        for name, (image, cam_from_world, inliers) in found.items():
            posed[name] = (image.camera_id, cam_from_world)
            references.add(image.image_id)
            observed.update(((image.image_id, kp), pid) for kp, pid in inliers)
        remaining = [im for im in remaining if im.name not in found]
        passes.append(len(found))
    return posed, passes


def absolute_pose(d, model, image, references: list[int], observed: dict):
    """`(cam_from_world, [(keypoint index, 3D point id) of the inliers])` of one database image,
    from its verified matches to the posed `references` whose keypoints see 3D points
    (`observed`), by LO-RANSAC PnP and refinement; or None."""
    import pycolmap

    corr = {}  # keypoint index -> 3D point id (first reference's match wins)
    for rid in references:
        matches = d.read_two_view_geometry(image.image_id, rid).inlier_matches
        if matches is None or len(matches) == 0:
            continue
        for mine, theirs in np.asarray(matches):  # (read in the order asked: this image's keypoint first)
            pid = observed.get((rid, int(theirs)))
            if pid is not None:
                corr.setdefault(int(mine), pid)
    if len(corr) < MIN_CORRESPONDENCES:
        return None
    idx = np.fromiter(corr, int)
    points2d = np.asarray(d.read_keypoints(image.image_id))[idx, :2].astype(np.float64)
    points3d = np.stack([model.points3D[corr[i]].xyz for i in idx]).astype(np.float64)
    camera = model.cameras[image.camera_id] if image.camera_id in model.cameras else None
    if camera is None:
        return None
    found = pycolmap.estimate_and_refine_absolute_pose(points2d, points3d, camera)
    if found is None or found["num_inliers"] < MIN_CORRESPONDENCES:
        return None
    inliers = idx[np.asarray(found["inlier_mask"], bool)]
    return found["cam_from_world"], [(int(k), corr[int(k)]) for k in inliers]
