"""What the pendant is served with: its security headers, the local API docs, and the scan's
points as gzip'd float32 for the 3-D view."""

from __future__ import annotations

import gzip

import numpy as np

from drivers.scanning.pointcloud import read_scan
from service.api import ui


def test_the_page_is_sent_with_a_strict_policy_and_its_import_map_by_hash(client):
    response = client.get("/")
    assert response.status_code == 200
    csp = response.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "'unsafe-inline'" not in csp
    assert "'sha256-" in csp  # the import map, allowed by its hash alone
    assert response.headers["referrer-policy"] == "no-referrer"
    script = client.get("/ui/js/app.js")
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert script.headers["content-security-policy"] == ui.policy()


def test_the_docs_name_only_local_assets(client):
    for path in ("/docs", "/redoc"):
        page = client.get(path).text
        assert "/ui/vendor/" in page
        assert "cdn." not in page and "fonts.googleapis" not in page


def test_scan_points_are_decimated_float32_gzip(client, session, tmp_path):
    sid = session
    scan_id = client.get(f"/sessions/{sid}").json()["scan_id"]
    ply = tmp_path / "scan.ply"
    ply.write_bytes(client.get(f"/sessions/{sid}/scans/{scan_id}/ply").content)
    full = read_scan(ply).scan.points_m
    # Read the raw body: the transport must not decompress it, the browser does.
    with client.stream("GET", f"/sessions/{sid}/scans/{scan_id}/points?max_points=1000") as raw:
        assert raw.status_code == 200
        assert raw.headers["content-encoding"] == "gzip"
        body = b"".join(raw.iter_raw())
    points = np.frombuffer(gzip.decompress(body), dtype="<f4").reshape(-1, 3)
    assert len(points) == int(raw.headers["x-point-count"]) <= 1000
    assert int(raw.headers["x-point-total"]) == len(full)
    step = -(-len(full) // 1000)
    np.testing.assert_allclose(points, full[::step], atol=1e-6)
    assert len(body) < points.nbytes  # compressed
    refused = client.get(f"/sessions/{sid}/scans/{scan_id}/points?max_points=0")
    assert refused.status_code == 422
