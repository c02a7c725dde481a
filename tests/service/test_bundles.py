"""Session bundles: export, import, round trips, and every way a bundle can be bad.

A session made through the API (recording, scan, calibration, reconstruction with its preview,
trajectory, dry run) is exported by the CLI and the API; the bundles are
imported into other data folders, exported again and compared byte for byte; damaged, tampered,
truncated, newer and hostile bundles are refused with a clear error and change nothing.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.bundles import (
    BUNDLE_SCHEMA,
    MANIFEST_NAME,
    BundleConflictError,
    BundleError,
    export_bundle,
    import_bundle,
)
from service.cli import main
from service.store import Store
from tests.service.conftest import AUTH, make_settings, planned_session, wait


@pytest.fixture(scope="module")
def source(tmp_path_factory, scene_files):
    """A data folder with one full session (and a second, empty one), served; its bundle."""
    data = tmp_path_factory.mktemp("source")
    with TestClient(create_app(make_settings(data)), headers=AUTH) as client:
        sid, trajectories = planned_session(client, scene_files, [0.05], name="bundled")
        dry = client.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectories[0.05]})
        assert wait(client, dry.json())["state"] == "succeeded"
        client.post("/sessions", json={"name": "other"})
        response = client.get(f"/sessions/{sid}/bundle")
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "application/zip"
        artifacts = client.get(f"/sessions/{sid}/artifacts").json()
        session = client.get(f"/sessions/{sid}").json()
    return {
        "data": data,
        "sid": sid,
        "zip": response.content,
        "artifacts": artifacts,
        "session": session,
    }


def _store(folder: Path) -> Store:
    return Store(folder, f"sqlite:///{folder / 'teachpath.db'}")


def _entries(content: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(content)) as bundle:
        return {info.filename: bundle.read(info) for info in bundle.infolist()}


def _rezip(entries: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as bundle:
        for name, content in entries.items():
            bundle.writestr(name, content)
    return out.getvalue()


def _with_manifest(content: bytes, change) -> bytes:
    entries = _entries(content)
    manifest = json.loads(entries[MANIFEST_NAME])
    change(manifest)
    entries[MANIFEST_NAME] = json.dumps(manifest).encode()
    return _rezip(entries)


def _state(folder: Path) -> tuple:
    """What an import may change: the database's sessions and artifacts and the files."""
    store = _store(folder)
    sessions = [(s.id, s.name) for s in store.sessions(include_deleted=True)]
    artifacts = sorted((a.id, a.sha256) for s in sessions for a in store.artifacts(s[0]))
    files = sorted(
        (str(p.relative_to(folder)), hashlib.sha256(p.read_bytes()).hexdigest())
        for p in folder.rglob("*")
        if p.is_file() and p.name not in ("teachpath.db", "teachpath.db-wal", "teachpath.db-shm")
    )
    return sessions, artifacts, files


def test_the_bundle_holds_the_session_every_artifact_and_their_checksums(source):
    entries = _entries(source["zip"])
    manifest = json.loads(entries[MANIFEST_NAME])
    assert manifest["format"] == "teachpath-session-bundle"
    assert manifest["schema_version"] == BUNDLE_SCHEMA
    assert manifest["teachpath_version"]
    assert manifest["session"]["id"] == source["sid"]
    assert manifest["session"]["T_base_tracker"] == source["session"]["T_base_tracker"]
    kinds = sorted(a["kind"] for a in manifest["artifacts"])
    assert kinds == ["execution", "reconstruction", "recording", "scan", "trajectory"]
    assert [a["id"] for a in manifest["artifacts"]] == [a["id"] for a in source["artifacts"]]
    listed = {}
    for artifact in manifest["artifacts"]:
        for entry in [artifact["data"], *artifact["files"]]:
            listed[entry["path"]] = entry
    assert set(entries) == set(listed) | {MANIFEST_NAME}
    for path, entry in listed.items():
        assert hashlib.sha256(entries[path]).hexdigest() == entry["sha256"]
        assert len(entries[path]) == entry["size"]
        assert entries[path] == (source["data"] / path).read_bytes()
    # The raw uploads as they came, the reconstruction's preview.
    paths = set(listed)
    assert any(p.startswith("uploads/rec_") for p in paths)
    assert any(p.startswith("uploads/scn_") for p in paths)
    assert any(p.startswith("arrays/rcn_") and p.endswith(".png") for p in paths)
    by_kind = {a["kind"]: a for a in manifest["artifacts"]}
    stored = {a["id"]: a for a in source["artifacts"]}
    for artifact in manifest["artifacts"]:
        assert artifact["params"] == stored[artifact["id"]]["params"]
        assert artifact["inputs"] == stored[artifact["id"]]["inputs"]
    assert by_kind["reconstruction"]["summary"]["n_points"] > 0


def test_export_import_export_gives_the_same_bytes_and_the_api_serves_the_import(source, tmp_path):
    """CLI export of the source equals the API's; imported elsewhere (CLI) and exported again,
    the manifest and every file are identical, and the service there serves the session."""
    first = tmp_path / "first.zip"
    assert (
        main(
            [
                "bundle",
                "export",
                source["sid"],
                "--data-dir",
                str(source["data"]),
                "--out",
                str(first),
            ]
        )
        == 0
    )
    assert first.read_bytes() == source["zip"]
    target = tmp_path / "target"
    assert main(["bundle", "import", str(first), "--data-dir", str(target)]) == 0
    second = tmp_path / "second.zip"
    assert (
        main(["bundle", "export", source["sid"], "--data-dir", str(target), "--out", str(second)])
        == 0
    )
    assert second.read_bytes() == first.read_bytes()
    with TestClient(create_app(make_settings(target)), headers=AUTH) as client:
        session = client.get(f"/sessions/{source['sid']}").json()
        assert session == source["session"]
        assert client.get(f"/sessions/{source['sid']}/artifacts").json() == source["artifacts"]
        rcn = next(a for a in source["artifacts"] if a["kind"] == "reconstruction")
        csv = client.get(f"/sessions/{source['sid']}/reconstructions/{rcn['id']}/csv")
        assert csv.status_code == 200 and csv.text.count("\n") > 100
        assert client.get(f"/sessions/{source['sid']}/bundle").content == source["zip"]


def test_importing_twice_gives_one_session_and_changes_nothing(source, tmp_path, capsys):
    target = tmp_path / "target"
    first = import_bundle(_store(target), source["zip"])
    assert (
        first.created and first.n_artifacts == 5 and first.n_files == 8
    )  # 5 arrays, 2 uploads, 1 preview
    before = _state(target)
    bundle = tmp_path / "b.zip"
    bundle.write_bytes(source["zip"])
    assert main(["bundle", "import", str(bundle), "--data-dir", str(target)]) == 0
    assert "already in" in capsys.readouterr().out
    again = import_bundle(_store(target), source["zip"])
    assert not again.created and again.session_id == source["sid"]
    assert _state(target) == before
    assert len(before[0]) == 1


def test_the_api_imports_a_bundle_once_then_says_it_was_there(source, tmp_path):
    with TestClient(create_app(make_settings(tmp_path / "d")), headers=AUTH) as client:
        files = {"file": ("s.zip", source["zip"], "application/zip")}
        first = client.post("/sessions/import", files=files)
        assert first.status_code == 201, first.text
        assert first.json()["created"] and first.json()["session"]["id"] == source["sid"]
        second = client.post("/sessions/import", files=files)
        assert second.status_code == 200 and not second.json()["created"]
        assert [s["id"] for s in client.get("/sessions").json()] == [source["sid"]]
        # The imported session works: plan its reconstruction again.
        rcn = next(a for a in source["artifacts"] if a["kind"] == "reconstruction")
        job = client.post(
            f"/sessions/{source['sid']}/trajectories",
            json={"reconstruction_id": rcn["id"], "speed_m_s": 0.05},
        ).json()
        assert wait(client, job)["state"] == "succeeded"
        # Now the session here differs from the bundle: a conflict, nothing changed.
        third = client.post("/sessions/import", files=files)
        assert third.status_code == 409 and third.json()["code"] == "bundle_conflict"
        assert "other content" in third.json()["message"]


def _tampered_file(content: bytes) -> bytes:
    entries = _entries(content)
    name = next(n for n in entries if n.startswith("arrays/rcn_") and n.endswith(".npz"))
    data = bytearray(entries[name])
    data[len(data) // 2] ^= 0xFF
    entries[name] = bytes(data)
    return _rezip(entries)


def _recomputed(content: bytes, edit) -> bytes:
    """A bundle edited with its checksums recomputed to match (a deliberate forgery)."""
    entries = _entries(content)
    manifest = json.loads(entries[MANIFEST_NAME])
    edit(entries, manifest)
    for artifact in manifest["artifacts"]:
        for entry in [artifact["data"], *artifact["files"]]:
            entry["sha256"] = hashlib.sha256(entries[entry["path"]]).hexdigest()
            entry["size"] = len(entries[entry["path"]])
    entries[MANIFEST_NAME] = json.dumps(manifest).encode()
    return _rezip(entries)


def _npz(arrays: dict) -> bytes:
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def _bomb_npz() -> bytes:
    out = io.BytesIO()
    np.savez_compressed(out, points_m=np.zeros((1_000_000, 3)))
    return out.getvalue()


def _first(manifest, kind):
    return next(a for a in manifest["artifacts"] if a["kind"] == kind)


def _encrypted(content: bytes) -> bytes:
    """The bundle with the scan's arrays flagged as encrypted (zipfile writes no such entry:
    the flag is set in the central directory's record of it)."""
    data = bytearray(content)
    with zipfile.ZipFile(io.BytesIO(content)) as bundle:
        name = next(n for n in bundle.namelist() if n.startswith("arrays/scn_")).encode()
    at = 0
    while True:
        at = data.index(b"PK\x01\x02", at)
        name_length = int.from_bytes(data[at + 28 : at + 30], "little")
        if data[at + 46 : at + 46 + name_length] == name:
            break
        at += 4
    data[at + 8] |= 0x1
    return bytes(data)


def _lzma(content: bytes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as bundle:
        for name, data in _entries(content).items():
            method = zipfile.ZIP_LZMA if name.endswith(".npz") else zipfile.ZIP_DEFLATED
            bundle.writestr(name, data, compress_type=method)
    return out.getvalue()


def _npy_that_lies() -> bytes:
    """An .npz whose stored member's header declares a terabyte of points."""
    member = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        member, {"descr": "<f8", "fortran_order": False, "shape": (10**11, 3)}
    )
    member.write(b"\0" * 64)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as npz:
        npz.writestr("points_m.npy", member.getvalue())
    return out.getvalue()


def _renamed_upload(entries, manifest, new_name: str) -> None:
    scan = _first(manifest, "scan")
    upload = next(f for f in scan["files"] if f["path"].startswith("uploads/"))
    renamed = upload["path"].rsplit("/", 1)[0] + "/" + new_name
    entries[renamed] = entries.pop(upload["path"])
    upload["path"] = renamed


BAD_BUNDLES = {
    "not a zip": (lambda z: b"PK\x03\x04 this is not a zip at all", "not a readable zip"),
    "empty": (lambda z: b"", "not a readable zip"),
    "truncated": (lambda z: z[: len(z) // 2], "not a readable zip"),
    "no manifest": (
        lambda z: _rezip({k: v for k, v in _entries(z).items() if k != MANIFEST_NAME}),
        "no manifest.json",
    ),
    "manifest not json": (
        lambda z: _rezip({**_entries(z), MANIFEST_NAME: b"{not json"}),
        "not valid JSON",
    ),
    "manifest a list": (lambda z: _rezip({**_entries(z), MANIFEST_NAME: b"[]"}), "JSON object"),
    "deeply nested": (
        lambda z: _rezip({**_entries(z), MANIFEST_NAME: b"[" * 100_000 + b"]" * 100_000}),
        "not valid JSON",
    ),
    "nested in a summary": (
        lambda z: _with_manifest(
            z, lambda m: m["artifacts"][0]["summary"].update(x=json.loads("[" * 500 + "]" * 500))
        ),
        "nested more than",
    ),
    "infinite number": (
        lambda z: _rezip(
            {
                **_entries(z),
                MANIFEST_NAME: _entries(z)[MANIFEST_NAME].replace(
                    b'"params": {', b'"params": {"x": 1e999, ', 1
                ),
            }
        ),
        "too large a number",
    ),
    "NaN": (
        lambda z: _rezip(
            {
                **_entries(z),
                MANIFEST_NAME: _entries(z)[MANIFEST_NAME].replace(
                    b'"params": {', b'"params": {"x": NaN, ', 1
                ),
            }
        ),
        "not a number JSON allows",
    ),
    "newer schema": (
        lambda z: _with_manifest(z, lambda m: m.update(schema_version=BUNDLE_SCHEMA + 1)),
        "newer teachpath",
    ),
    "other format": (lambda z: _with_manifest(z, lambda m: m.update(format="zip")), "format"),
    "unknown kind": (
        lambda z: _with_manifest(z, lambda m: m["artifacts"][0].update(kind="weapon")),
        "kind",
    ),
    "extra field": (lambda z: _with_manifest(z, lambda m: m.update(extra=1)), "extra"),
    "bad session id": (
        lambda z: _with_manifest(z, lambda m: m["session"].update(id="../../etc")),
        "not a session id",
    ),
    "calibration not rigid": (
        lambda z: _with_manifest(
            z, lambda m: m["session"].update(T_base_tracker=[[2, 0, 0, 0]] * 3 + [[0, 0, 0, 1]])
        ),
        "T_base_tracker",
    ),
    "tampered file": (_tampered_file, "does not match its checksum"),
    "size that lies": (
        lambda z: _with_manifest(z, lambda m: m["artifacts"][0]["data"].update(size=10**12)),
        "the zip says",
    ),
    "missing file": (
        lambda z: _rezip({k: v for k, v in _entries(z).items() if not k.startswith("arrays/rec_")}),
        "missing",
    ),
    "extra file": (
        lambda z: _rezip({**_entries(z), "../../outside.txt": b"x"}),
        "does not list",
    ),
    "path that climbs out": (
        lambda z: _recomputed(
            z,
            lambda e, m: (
                e.update({"uploads/../../../x": b"x"}),
                _first(m, "scan")["files"].append(
                    {"path": "uploads/../../../x", "sha256": "0" * 64, "size": 1}
                ),
            ),
        ),
        "not a file teachpath keeps",
    ),
    "id of another kind": (
        lambda z: _with_manifest(z, lambda m: _first(m, "scan").update(kind="recording")),
        "is not the id of a recording",
    ),
    "forged arrays": (
        lambda z: _recomputed(
            z,
            lambda e, m: e.update({_first(m, "scan")["data"]["path"]: _npz({"x": np.zeros(3)})}),
        ),
        "does not hold what a scan holds",
    ),
    "bomb in the arrays": (
        lambda z: _recomputed(
            z, lambda e, m: e.update({_first(m, "scan")["data"]["path"]: _bomb_npz()})
        ),
        "compressed or encrypted members",
    ),
    "forged summary": (
        lambda z: _recomputed(
            z, lambda e, m: _first(m, "trajectory")["summary"].update(duration_s="long")
        ),
        "does not hold what a trajectory holds",
    ),
    "encrypted entry": (_encrypted, "is encrypted"),
    "other compression": (_lzma, "compressed with method 14"),
    "hidden upload name": (
        lambda z: _recomputed(z, lambda e, m: _renamed_upload(e, m, ".hidden")),
        "not a file teachpath keeps",
    ),
    "array header that lies": (
        lambda z: _recomputed(
            z, lambda e, m: e.update({_first(m, "scan")["data"]["path"]: _npy_that_lies()})
        ),
        "declares",
    ),
    "recording id not in the bundle": (
        lambda z: _with_manifest(z, lambda m: m["session"].update(recording_id="rec_000000000000")),
        "not among its artifacts",
    ),
}


@pytest.mark.parametrize("case", list(BAD_BUNDLES))
def test_a_bad_bundle_is_refused_by_name_and_changes_nothing(source, tmp_path, case):
    make, message = BAD_BUNDLES[case]
    bad = make(source["zip"])
    target = tmp_path / "target"
    store = _store(target)
    store.create_session("kept")
    before = _state(target)
    with pytest.raises(BundleError) as refused:
        import_bundle(store, bad)
    assert message in str(refused.value)
    assert not isinstance(refused.value, BundleConflictError)
    assert _state(target) == before
    assert not list(target.rglob(".*import*"))


def test_the_api_and_cli_refuse_bad_bundles_with_their_reason(source, tmp_path, capsys):
    bad = BAD_BUNDLES["tampered file"][0](source["zip"])
    with TestClient(create_app(make_settings(tmp_path / "d")), headers=AUTH) as client:
        for content in (bad, b"", b"x" * 100, BAD_BUNDLES["newer schema"][0](source["zip"])):
            response = client.post("/sessions/import", files={"file": ("b.zip", content)})
            assert response.status_code == 422, response.text
            assert response.json()["code"] in ("bundle_invalid", "invalid_file")
        assert client.get("/sessions").json() == []
        assert client.get("/sessions/ses_000000000000/bundle").status_code == 404
        too_big = client.post("/sessions/import", files={"file": ("b.zip", b"x" * (6 << 20))})
        assert too_big.status_code == 413
    path = tmp_path / "bad.zip"
    path.write_bytes(bad)
    assert main(["bundle", "import", str(path), "--data-dir", str(tmp_path / "d")]) == 1
    assert "does not match its checksum" in capsys.readouterr().err
    assert main(["bundle", "import", str(tmp_path / "none.zip"), "--data-dir", str(tmp_path)]) == 1

    def export(data_dir) -> int:
        out = str(tmp_path / "x.zip")
        return main(
            ["bundle", "export", "ses_000000000000", "--data-dir", str(data_dir), "--out", out]
        )

    assert export(source["data"]) == 1
    assert "no session" in capsys.readouterr().err
    assert export(tmp_path / "empty") == 1
    assert "holds no teachpath database" in capsys.readouterr().err
    assert not (tmp_path / "x.zip").exists()


def test_an_artifact_id_of_another_session_or_a_deleted_session_is_a_conflict(source, tmp_path):
    target = tmp_path / "target"
    store = _store(target)
    import_bundle(store, source["zip"])
    # The same artifacts under another session id.
    other = _with_manifest(source["zip"], lambda m: m["session"].update(id="ses_0000000000aa"))
    with pytest.raises(BundleConflictError, match="already belongs to session"):
        import_bundle(store, other)
    from service.store import now

    store.update_session(source["sid"], deleted_at=now())
    with pytest.raises(BundleConflictError, match="was deleted"):
        import_bundle(store, source["zip"])


def test_a_damaged_data_folder_is_not_exported(source, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(source["data"], copy)
    store = _store(copy)
    row = next(a for a in store.artifacts(source["sid"]) if a.kind == "scan")
    path = copy / row.path
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(BundleError, match="no longer match their checksum"):
        export_bundle(store, source["sid"], tmp_path / "out.zip")
    assert not (tmp_path / "out.zip").exists()


def test_two_processes_importing_the_same_ids_at_once_leave_one_consistent_session(
    source, tmp_path
):
    """The CLI in two processes imports two bundles of the same session ids, one renamed: one
    wins, the other is refused as a conflict, and the winner's session exports to its bundle."""
    import subprocess
    import sys

    other = _with_manifest(source["zip"], lambda m: m["session"].update(name="renamed"))
    paths = [tmp_path / "a.zip", tmp_path / "b.zip"]
    paths[0].write_bytes(source["zip"])
    paths[1].write_bytes(other)
    target = tmp_path / "target"
    _store(target)  # the database exists before both start
    for _ in range(3):
        runs = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "service.cli",
                    "bundle",
                    "import",
                    str(p),
                    "--data-dir",
                    str(target),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for p in paths
        ]
        results = [(run.wait(120), run.stdout.read(), run.stderr.read()) for run in runs]
        codes = sorted(code for code, _, _ in results)
        assert codes == [0, 1], results  # later rounds: the winner's is "already here"
        (session,) = _store(target).sessions()
        winner = paths[0] if session.name == "bundled" else paths[1]
        out = tmp_path / "again.zip"
        export_bundle(_store(target), source["sid"], out)
        exported, won = _entries(out.read_bytes()), _entries(winner.read_bytes())
        # The renamed bundle's manifest was written compactly by this test: compare content.
        assert json.loads(exported.pop(MANIFEST_NAME)) == json.loads(won.pop(MANIFEST_NAME))
        assert exported == won
        for code, _, err in results:
            assert code == 0 or "other content" in err or "meanwhile" in err, err


def test_a_service_starting_during_an_import_leaves_the_files_it_writes(tmp_path):
    """An import (here, from the command line) writes its files before it records them: a
    service starting meanwhile must not remove them as a crash's leftovers; once alone, it
    removes files no artifact names."""
    data = tmp_path / "d"
    store = _store(data)
    pending = data / "arrays" / "rec_0123456789ab.npz"
    pending.write_bytes(b"not yet recorded")
    settings = make_settings(data, database_url=f"sqlite:///{data / 'teachpath.db'}")
    with store.presence("import"):
        with TestClient(create_app(settings), headers=AUTH):
            pass
        assert pending.exists()
    with TestClient(create_app(settings), headers=AUTH):
        pass
    assert not pending.exists()


def _zeros_npz(megabytes: int) -> bytes:
    """An honest npz (members stored, headers true) of zeros: tiny once the bundle deflates it."""
    return _npz({"points_m": np.zeros((megabytes * (1 << 20) // 24, 3))})


def test_a_member_that_unpacks_far_beyond_its_compressed_size_is_refused(source, tmp_path):
    """A 1.6 MB bundle held a 1.5 GB array: every check passed (the npz's headers were true)
    and the server went to 3.3 GB. Now no member unpacks to over 100x its compressed size."""
    bomb = _recomputed(
        source["zip"],
        lambda e, m: e.update({_first(m, "scan")["data"]["path"]: _zeros_npz(60)}),
    )
    assert len(bomb) < len(source["zip"]) + 1_000_000  # 60 MB in well under 1 MB more
    target = tmp_path / "target"
    before = _state(target) if target.exists() else None
    with pytest.raises(BundleError, match="more than 100 times"):
        import_bundle(_store(target), bomb)
    assert before is None or _state(target) == before
    assert _store(target).sessions() == []


def test_the_service_holds_each_file_of_a_bundle_to_the_upload_limit(source, tmp_path):
    """Imported through the API, a file larger than an upload may be is refused, naming the
    setting (the test server's limit is 5 MB)."""
    rng = np.random.default_rng(0)
    # 7 MB unpacked that deflates about 20x: under the request's 5 MB, within the ratio.
    big = _npz({"points_m": rng.integers(0, 4, size=(300_000, 3)).astype(np.float64)})
    bundle = _recomputed(
        source["zip"], lambda e, m: e.update({_first(m, "scan")["data"]["path"]: big})
    )
    with TestClient(create_app(make_settings(tmp_path / "d")), headers=AUTH) as client:
        response = client.post(
            "/sessions/import", files={"file": ("s.zip", bundle, "application/zip")}
        )
        assert response.status_code == 422, response.text
        assert "TEACHPATH_MAX_UPLOAD_MB" in response.json()["message"]
        assert client.get("/sessions").json() == []


def _upload_of(manifest, kind) -> str:
    return next(
        f["path"] for f in _first(manifest, kind)["files"] if f["path"].startswith("uploads/")
    )


def _shifted_trace(csv: bytes) -> bytes:
    """The trace with its tenth sample moved by 1 mm: a valid file, not the one the arrays
    came from."""
    lines = csv.decode().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if line[:1].isdigit() or line[:1] == "-")
    fields = lines[header + 10].rstrip("\n").split(",")
    fields[1] = repr(float(fields[1]) + 0.001)
    lines[header + 10] = ",".join(fields) + "\n"
    return "".join(lines).encode()


RAW_UPLOAD_CASES = {
    # A raw file that reads, but into other arrays than the bundle's: a forgery (or a mix-up).
    "a trace that is not the arrays' trace": (
        "recording",
        lambda raw: _shifted_trace(raw),
        "are not what its original file",
    ),
    "a scan that is not the arrays' scan": (
        "scan",
        lambda raw: raw[: len(raw) // 2],
        "cannot be read as an upload here",
    ),
    "bytes no reader reads": (
        "recording",
        lambda raw: bytes(range(256)) * 64,
        "cannot be read as an upload here",
    ),
    # Hostile: 200k columns held a parse slot 300 s; as a bundle's raw file it is read by the
    # same reader, within the same bounds.
    "a CSV of 200k columns": (
        "recording",
        lambda raw: (",".join(f"c{i}" for i in range(200_000)) + "\n").encode(),
        "columns",
    ),
}


@pytest.mark.parametrize("case", RAW_UPLOAD_CASES)
def test_a_raw_upload_in_a_bundle_is_read_again_as_an_upload_and_must_give_its_arrays(
    source, tmp_path, case
):
    """A bundle's raw files were only checksummed: a forged bundle could carry any bytes as
    "the original file". Each is read again by the upload's reader, options and limits, and
    must give the bundle's own arrays; otherwise nothing is imported, and the reason is said."""
    kind, edit, message = RAW_UPLOAD_CASES[case]

    def swap(entries, manifest):
        path = _upload_of(manifest, kind)
        entries[path] = edit(entries[path])

    forged = _recomputed(source["zip"], swap)
    with TestClient(create_app(make_settings(tmp_path / "d")), headers=AUTH) as client:
        response = client.post(
            "/sessions/import", files={"file": ("s.zip", forged, "application/zip")}
        )
        assert response.status_code == 422, response.text
        body = response.json()
        assert body["code"] == "bundle_invalid"
        assert message in body["message"], body["message"]
        assert client.get("/sessions").json() == []
    assert not list((tmp_path / "d" / "uploads").iterdir())
    assert not list((tmp_path / "d" / "arrays").iterdir())


def test_the_cli_reads_a_bundles_raw_uploads_again_too(source, tmp_path, capsys):
    forged = _recomputed(
        source["zip"],
        lambda e, m: e.update(
            {_upload_of(m, "recording"): _shifted_trace(e[_upload_of(m, "recording")])}
        ),
    )
    bundle = tmp_path / "forged.zip"
    bundle.write_bytes(forged)
    assert main(["bundle", "import", str(bundle), "--data-dir", str(tmp_path / "cell")]) == 1
    assert "are not what its original file" in capsys.readouterr().err
    assert _store(tmp_path / "cell").sessions() == []


def test_an_artifact_may_keep_one_raw_upload_and_only_if_its_kind_has_one(source, tmp_path):
    def second_upload(entries, manifest):
        artifact = _first(manifest, "recording")
        path = f"uploads/{artifact['id']}/again.csv"
        entries[path] = entries[_upload_of(manifest, "recording")]
        artifact["files"].append({"path": path, "sha256": "0" * 64, "size": 0})

    def upload_on_a_plan(entries, manifest):
        artifact = _first(manifest, "trajectory")
        path = f"uploads/{artifact['id']}/plan.csv"
        entries[path] = b"t,x\n0,0\n"
        artifact["files"].append({"path": path, "sha256": "0" * 64, "size": 0})

    for edit, message in (
        (second_upload, "lists 2 uploaded files"),
        (upload_on_a_plan, "keeps none"),
    ):
        with pytest.raises(BundleError, match=message):
            import_bundle(_store(tmp_path / "t"), _recomputed(source["zip"], edit))
    assert _store(tmp_path / "t").sessions() == []
