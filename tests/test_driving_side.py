"""Which side traffic keeps to, from the lane map (magail_sumo/scene/driving_side.py), and
left-hand networks for left-hand scenes (netconvert --lefthand)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from converters import load_scene
from magail_sumo.scene import Scene
from magail_sumo.scene.driving_side import driving_side

SHARED = Path(os.environ.get("MAGAIL_SUMO_SHARED_DATA", ROOT.parent / "shared" / "data"))
NUSCENES = sorted((SHARED / "scenarionet").glob("nuscenes*/*.pkl")) if SHARED.is_dir() else []


def mirrored(scene: Scene) -> Scene:
    """The scene reflected across the y axis (x -> -x, headings mirrored): the same roads with
    traffic on the other side."""
    def flip(a: np.ndarray) -> np.ndarray:
        a = np.array(a, np.float64)
        a[..., 0] = -a[..., 0]
        return a

    rm = scene.roadmap
    roadmap = dataclasses.replace(
        rm, lanes=tuple(dataclasses.replace(l, polyline=flip(l.polyline)) for l in rm.lanes),
        road_edges=tuple(dataclasses.replace(e, polyline=flip(e.polyline))
                         for e in rm.road_edges),
        road_lines=tuple(dataclasses.replace(e, polyline=flip(e.polyline))
                         for e in rm.road_lines))
    tr = scene.tracks
    tracks = dataclasses.replace(tr, x=-tr.x, vx=-tr.vx, heading=np.pi - tr.heading)
    return dataclasses.replace(scene, roadmap=roadmap, tracks=tracks)


def test_womd_keeps_right_and_its_mirror_image_keeps_left():
    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    side = driving_side(scene.roadmap)
    assert side.side == "right" and side.right_votes > 10 * max(1, side.left_votes)
    flipped = driving_side(mirrored(scene).roadmap)
    assert flipped.side == "left"
    assert (flipped.left_votes, flipped.right_votes) == (side.right_votes, side.left_votes)


def test_a_map_without_two_way_roads_does_not_say():
    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    one_way = dataclasses.replace(scene.roadmap, lanes=scene.roadmap.lanes[:1])
    assert driving_side(one_way).side is None


@pytest.mark.parametrize("path", NUSCENES, ids=lambda p: p.stem)
def test_nuscenes_singapore_keeps_left_boston_right(path):
    from converters.scenarionet import safe_loads

    where = safe_loads(path.read_bytes())["metadata"]["map"]
    want = "left" if where.startswith("singapore") else "right"
    assert driving_side(load_scene(path).roadmap).side == want, where


@pytest.mark.sumo
def test_a_left_hand_scene_converts_to_a_left_hand_network(tmp_path):
    from converters.sumo import ConvertOptions, convert_scene

    scene = mirrored(load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord"))
    rep = convert_scene(scene, tmp_path, ConvertOptions(baseline=False))
    assert rep.status == "ok", rep.reason
    assert rep.data_quality["driving_side"]["side"] == "left"
    net = next(tmp_path.glob("*/*.net.xml")).read_text()
    assert 'lefthand="true"' in net[:2000]
    assert rep.quality["route_rate"] >= 0.95
