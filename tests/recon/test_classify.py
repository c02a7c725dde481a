"""Segment kinds: a string enum, so stored segments read and compare as plain strings."""

import json
from dataclasses import asdict

import pytest

from recon import scenes
from recon.classify import SegmentKind, classify_segments
from recon.recon_params import ReconParams
from recon.reconstruct import plan_segments, prepare_scan_model
from recon.results import Segment
from recon.transforms import apply_transform


def test_segment_json_keeps_the_plain_strings():
    segments = [Segment(0, 10, kind, 0.5) for kind in SegmentKind]
    text = json.dumps([asdict(s) for s in segments])
    assert [s["kind"] for s in json.loads(text)] == ["edge", "surface", "path"]
    assert json.dumps(SegmentKind.EDGE) == '"edge"' and str(SegmentKind.PATH) == "path"


def test_kinds_compare_equal_to_their_strings_and_are_read_back_from_them():
    assert SegmentKind.EDGE == "edge" and SegmentKind.SURFACE != "edge"
    read_back = Segment(**json.loads(json.dumps(asdict(Segment(3, 9, SegmentKind.SURFACE, 0.1)))))
    assert read_back.kind is SegmentKind.SURFACE
    assert read_back == Segment(3, 9, SegmentKind.SURFACE, 0.1)
    with pytest.raises(ValueError, match="'ridge' is not a valid SegmentKind"):
        Segment(0, 4, "ridge", 0.0)


def test_the_box_corner_segments_follow_edges_and_the_trace_without_a_scan_nothing():
    scene = scenes.box_corner(0)
    params = ReconParams()
    plan = plan_segments(scene.recording, params)
    points = plan.resampled.points_m
    prepared = prepare_scan_model(points, scene.scan, plan.bounds, params)
    model, T = prepared.model, prepared.T_scan_tracker
    classes = classify_segments(apply_transform(T, points), plan.bounds, model, params)
    assert [c.kind for c in classes] == [SegmentKind.EDGE, SegmentKind.EDGE]
    assert all(c.edge_fraction > 0.9 for c in classes)
    far = apply_transform(T, points) + [0.0, 0.0, 0.5]  # half a metre above the workpiece
    assert [c.kind for c in classify_segments(far, plan.bounds, model, params)] == [
        SegmentKind.PATH,
        SegmentKind.PATH,
    ]
