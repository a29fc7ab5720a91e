"""What the scene's markers are in the fake Motive (``FakeMotive`` in ``fake.py`` uses it): one
asset — a rigid body, a one-bone skeleton or a NatNet 4.1 trained markerset — its model
definitions, and its frame content.

The asset's layout is the markers as seen at start, about their centroid; each frame the pose
is fitted (Kabsch) from the visible markers to that layout; with fewer than three visible
markers the asset is untracked. Visible markers are labeled markers ``(asset id, index + 1)``;
an invisible one is sent occluded at its model-predicted position while the asset is tracked
and omitted otherwise. Positions are in metres (Motive's default).
"""

from __future__ import annotations

import math

import numpy as np

from drivers.natnet import codec
from drivers.sim.scene import MarkerScene

#: What the scene's markers are in Motive: a rigid body (default), a one-bone skeleton, or a
#: NatNet 4.1 trained markerset with one bone. All share the asset's id and name.
ASSET_KINDS = ("rigid_body", "skeleton", "trained_markerset")
#: The fake skeleton's / trained markerset's single bone: id and name.
BONE_ID, BONE_NAME = 1, "plate"


def quat_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a 3×3 rotation matrix."""
    m = r
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def kabsch(local: np.ndarray, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with ``seen ≈ local @ R.T + t``; local, seen shape (n, 3), n ≥ 3."""
    cl, cs = local.mean(axis=0), seen.mean(axis=0)
    h = (local - cl).T @ (seen - cs)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cs - r @ cl


class FakeAsset:
    """The scene's markers for ``sensor`` as one Motive asset.

    scene: gives the markers (``observe(sensor)``, positions in mm, sensor frame). kind: one of
    ``ASSET_KINDS``. ident, name: the asset's id (1..65535) and name. ``learn_layout()`` (at
    the server's start) takes the markers as they are as the asset's layout.
    """

    def __init__(self, scene: MarkerScene, sensor: str, kind: str, ident: int, name: str) -> None:
        self.scene = scene
        self.sensor = sensor
        self.kind = kind
        self.ident = ident
        self.name = name
        self.marker_names: list[str] = []
        self.layout_m: np.ndarray | None = None  # (n, 3) reference layout about its centroid, m

    def learn_layout(self) -> None:
        """Take the scene's markers now as the layout; ValueError when it has none."""
        obs = self.scene.observe(self.sensor)
        if not obs:
            raise ValueError(f"scene reports no markers for sensor {self.sensor!r}")
        self.marker_names = [o.name for o in obs]
        pos_m = np.array([o.position_mm for o in obs], dtype=float) / 1000.0
        self.layout_m = pos_m - pos_m.mean(axis=0)

    def model_def(self) -> codec.ModelDef:
        """The asset's MODELDEF: its description and its marker set (marker offsets in m)."""
        assert self.layout_m is not None
        markers = tuple(
            codec.RigidBodyMarkerDescription(tuple(float(v) for v in p), 0, name)
            for p, name in zip(self.layout_m, self.marker_names)
        )
        marker_set = codec.MarkerSetDescription(self.name, tuple(self.marker_names))
        if self.kind == "rigid_body":
            body = codec.RigidBodyDescription(self.name, self.ident, -1, (0.0, 0.0, 0.0), markers)
            return codec.ModelDef((body, marker_set))
        bone = codec.RigidBodyDescription(BONE_NAME, BONE_ID, -1, (0.0, 0.0, 0.0), markers)
        if self.kind == "skeleton":
            skeleton = codec.SkeletonDescription(self.name, self.ident, (bone,))
            return codec.ModelDef((marker_set, skeleton))
        asset_markers = tuple(
            codec.AssetMarkerDescription(name, (self.ident << 16) | (i + 1),
                                         tuple(float(v) for v in p), 0.014, 0)
            for i, (p, name) in enumerate(zip(self.layout_m, self.marker_names))
        )
        return codec.ModelDef((marker_set, codec.AssetDescription(self.name, 0, self.ident, (bone,), asset_markers)))

    def frame(self, frame_no: int, timestamp: float, now_ticks: int, clock_frequency: int) -> codec.FrameOfData:
        """Frame ``frame_no`` from the scene as it is now; ``timestamp`` (s) and the tick
        stamps (``now_ticks`` at ``clock_frequency`` Hz: mid-exposure 5 ms and data received
        1 ms before transmit) as Motive sets them."""
        assert self.layout_m is not None
        by_name = {o.name: o for o in self.scene.observe(self.sensor)}
        n = len(self.marker_names)
        seen = np.full((n, 3), np.nan)
        vis = np.zeros(n, dtype=bool)
        for i, name in enumerate(self.marker_names):
            o = by_name.get(name)
            if o is not None:
                seen[i] = np.asarray(o.position_mm, dtype=float) / 1000.0
                vis[i] = bool(o.visible)
        rb, predicted = self._pose(seen, vis)
        labeled = self._labeled(seen, vis, predicted)
        set_pos = np.where(vis[:, None], seen, predicted if predicted is not None else 0.0)
        skeletons, assets = (), ()
        if self.kind != "rigid_body":  # the plate is the asset's one bone
            rb["id"] = (self.ident << 16) | BONE_ID
            if self.kind == "skeleton":
                skeletons = (codec.SkeletonData(self.ident, rb),)
            else:  # trained markerset: its markers go with the asset, not the labeled list
                assets = (codec.AssetData(self.ident, rb, labeled),)
                labeled = labeled[:0]
            rb = rb[:0]
        return codec.FrameOfData(
            frame_number=frame_no,
            marker_sets=(codec.MarkerSetData(self.name, set_pos.astype("<f4")),),
            unlabeled=seen[vis].astype("<f4").reshape(-1, 3),
            rigid_bodies=rb,
            skeletons=skeletons,
            assets=assets,
            labeled_markers=labeled,
            timestamp=timestamp,
            stamp_camera_mid_exposure=now_ticks - clock_frequency // 200,
            stamp_data_received=now_ticks - clock_frequency // 1000,
            stamp_transmit=now_ticks,
        )

    def _pose(self, seen: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The asset's rigid-body row (1,) fitted to the visible markers (``seen`` (n, 3) m,
        ``vis`` (n,)), and the layout's predicted positions (n, 3) m (None: untracked)."""
        rb = np.zeros(1, dtype=codec.RIGID_BODY_DTYPE)
        rb["id"] = self.ident
        if int(vis.sum()) < 3:
            rb["quat"] = (0.0, 0.0, 0.0, 1.0)
            return rb, None
        r, t = kabsch(self.layout_m[vis], seen[vis])
        predicted = self.layout_m @ r.T + t
        err = np.linalg.norm(predicted[vis] - seen[vis], axis=1)
        rb["pos"] = t
        rb["quat"] = quat_xyzw(r)
        rb["mean_error"] = float(err.mean())
        rb["params"] = codec.RIGID_BODY_TRACKED
        return rb, predicted

    def _labeled(self, seen: np.ndarray, vis: np.ndarray, predicted: np.ndarray | None) -> np.ndarray:
        """Labeled-marker rows: visible markers where seen, occluded ones at their predicted
        position while tracked (omitted otherwise)."""
        rows = []
        for i in range(len(self.marker_names)):
            mid = (self.ident << 16) | (i + 1)
            if vis[i]:
                res = float(np.linalg.norm(predicted[i] - seen[i])) if predicted is not None else 0.0
                rows.append((mid, seen[i], 0.014, codec.MARKER_PC_SOLVED | codec.MARKER_HAS_MODEL, res))
            elif predicted is not None:
                flags = codec.MARKER_OCCLUDED | codec.MARKER_MODEL_SOLVED | codec.MARKER_HAS_MODEL
                rows.append((mid, predicted[i], 0.014, flags, 0.0))
        labeled = np.zeros(len(rows), codec.LABELED_MARKER_DTYPE)
        for k, row in enumerate(rows):
            labeled[k] = row
        return labeled
