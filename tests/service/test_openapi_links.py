"""The OpenAPI links between operations (service/api/links.py): present in /openapi.json, naming
operations, parameters and response fields that exist."""

from __future__ import annotations

import copy
import re

import pytest
from fastapi.openapi.models import OpenAPI
from fastapi.testclient import TestClient

from service.api import links
from service.app import create_app
from tests.service.conftest import AUTH, make_settings


@pytest.fixture(scope="module")
def spec(tmp_path_factory) -> dict:
    app = create_app(make_settings(tmp_path_factory.mktemp("data")))
    with TestClient(app, headers=AUTH) as client:
        response = client.get("/openapi.json")
    assert response.status_code == 200
    return response.json()


def _operations(spec: dict) -> dict[str, tuple[str, str, dict]]:
    """operationId -> (method, path, operation)."""
    return {
        operation["operationId"]: (method.upper(), path, operation)
        for path, item in spec["paths"].items()
        for method, operation in item.items()
    }


def _deref(spec: dict, schema: dict) -> dict:
    while "$ref" in schema:
        target = spec
        for part in schema["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        schema = target
    return schema


def _has_pointer(spec: dict, schema: dict, parts: list[str]) -> bool:
    """Whether a JSON pointer (its segments) can hold a value in an instance of ``schema``."""
    schema = _deref(spec, schema)
    if not parts:
        return True
    for option in schema.get("anyOf", []):
        if _has_pointer(spec, option, parts):
            return True
    head, rest = parts[0], parts[1:]
    if schema.get("type") == "array" and head.isdigit():
        return _has_pointer(spec, schema.get("items", {}), rest)
    if schema.get("type") == "object" or "properties" in schema:
        if head in schema.get("properties", {}):
            return _has_pointer(spec, schema["properties"][head], rest)
        # dict[str, Any]: a job's result and parameters name what the job made.
        return schema.get("additionalProperties") is True or not schema.get("properties")
    return False


def _declared(spec: dict):
    """(source method, path, status, response, link name, link) of every link in the spec."""
    for path, item in spec["paths"].items():
        for method, operation in item.items():
            for status, response in operation["responses"].items():
                for name, link in response.get("links", {}).items():
                    yield method.upper(), path, status, operation, response, name, link


def test_the_spec_with_its_links_is_a_valid_openapi_document(spec):
    OpenAPI.model_validate(spec)
    declared = list(_declared(spec))
    assert len(declared) == sum(len(entries) for entries in links.LINKS.values())
    assert len(declared) > 50


def test_the_main_chains_are_linked(spec):
    by_source = {(m, p, s): response["links"] for m, p, s, _o, response, _n, _l in _declared(spec)}
    operations = _operations(spec)

    def targets(method, path, status):
        return {
            operations[link["operationId"]][:2] for link in by_source[method, path, status].values()
        }

    session = "/sessions/{session_id}"
    assert {
        ("GET", session),
        ("DELETE", session),
        ("PUT", session + "/recording"),
        ("PUT", session + "/scan"),
        ("PUT", session + "/calibration"),
        ("POST", session + "/reconstructions"),
        ("GET", session + "/artifacts"),
    } <= targets("POST", "/sessions", "201")
    jobs = {("GET", "/jobs/{job_id}"), ("POST", "/jobs/{job_id}/cancel")}
    for kind in ("reconstructions", "trajectories", "executions"):
        assert jobs <= targets("POST", f"{session}/{kind}", "202")
    assert {
        ("GET", session + "/recordings/{artifact_id}"),
        ("GET", session + "/recordings/{artifact_id}/csv"),
    } <= targets("PUT", session + "/recording", "201")
    assert ("POST", session + "/trajectories") in targets("GET", "/jobs/{job_id}", "200")
    assert ("POST", session + "/executions") in targets(
        "GET", session + "/trajectories/{artifact_id}", "200"
    )


def test_every_link_names_what_exists(spec):
    operations = _operations(spec)
    for method, path, status, source, response, name, link in _declared(spec):
        where = f"{method} {path} {status} {name}"
        assert link["operationId"] in operations, where
        _, _target_path, target = operations[link["operationId"]]
        path_parameters = {p["name"] for p in target.get("parameters", []) if p["in"] == "path"}
        # Every path parameter of the target is set (the link is followed with real ids).
        assert set(link["parameters"]) == path_parameters, where
        source_path = {p["name"] for p in source.get("parameters", []) if p["in"] == "path"}
        body_schema = response["content"]["application/json"]["schema"]
        expressions = list(link["parameters"].values())
        request_body = link.get("requestBody")
        if request_body is not None:
            target_body = target["requestBody"]["content"]["application/json"]["schema"]
            fields = _deref(spec, target_body)["properties"]
            assert set(request_body) <= set(fields), where
            expressions += re.findall(r"\$[^\"']+", str(request_body))
        for expression in expressions:
            if expression.startswith("$request.path."):
                assert expression.removeprefix("$request.path.") in source_path, where
            else:
                assert expression.startswith("$response.body#/"), where
                pointer = expression.removeprefix("$response.body#/").split("/")
                assert _has_pointer(spec, body_schema, pointer), (where, expression)


def test_a_link_to_a_missing_route_is_refused(monkeypatch, spec):
    broken = links.Link("nowhere", "GET", "/sessions/{session_id}/nowhere", "nothing")
    monkeypatch.setattr(links, "LINKS", {("POST", "/sessions", 201): [broken]})
    with pytest.raises(ValueError, match="missing operation GET /sessions/{session_id}/nowhere"):
        links.add_links(copy.deepcopy(spec))


def test_a_link_without_a_target_path_parameter_is_refused(monkeypatch, spec):
    broken = links.Link("typo", "GET", links.SESSION, "the session", {"sesion_id": "$x"})
    monkeypatch.setattr(links, "LINKS", {("POST", "/sessions", 201): [broken]})
    with pytest.raises(ValueError, match="no path parameter sesion_id"):
        links.add_links(copy.deepcopy(spec))
