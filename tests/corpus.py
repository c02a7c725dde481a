"""The corpus of files no one on the project made (``../shared/corpus`` beside the checkout, or
``TEACHPATH_CORPUS``): real CAD parts with their true feature curves, and files written by real
trackers, scanners and tools. Read in place, never copied into the project.

Tests that need it skip, saying so, where it is absent.
"""

from __future__ import annotations

import importlib.util
import os
from functools import cache
from pathlib import Path

import pytest

#: Environment variable naming the corpus folder (the one holding ``groundtruth/``).
CORPUS_ENV = "TEACHPATH_CORPUS"
ROOT = Path(__file__).resolve().parent.parent


def corpus_dir() -> Path | None:
    """The corpus folder, or None where there is none."""
    named = os.environ.get(CORPUS_ENV)
    candidates = [Path(named)] if named else []
    candidates.append(ROOT.parent / "shared" / "corpus")
    for path in candidates:
        if (path / "groundtruth" / "extract.py").is_file():
            return path
    return None


def require_corpus() -> Path:
    """The corpus folder; skips the calling test where it is absent."""
    path = corpus_dir()
    if path is None:
        pytest.skip(
            f"the external corpus is absent (looked in {ROOT.parent / 'shared' / 'corpus'} "
            f"and ${CORPUS_ENV}): the real-parts checks need it"
        )
    return path


@cache
def groundtruth_loader():
    """The corpus's own loader of the CAD parts and their true curves (``extract.py``),
    imported from where it lies."""
    path = corpus_dir()
    if path is None:
        raise FileNotFoundError("the external corpus is absent")
    spec = importlib.util.spec_from_file_location(
        "teachpath_corpus_extract", path / "groundtruth" / "extract.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@cache
def load_part(name: str):
    """A corpus part stood on the table (:func:`recon.scenes.cad.stood_on_table`), its true
    curves with it, at the corpus's 0.3 m bounding-box diagonal."""
    from recon.scenes.cad import stood_on_table

    loader = groundtruth_loader()
    (spec,) = [s for s in loader.MODELS if s["name"] == name]
    model = loader.load_model(spec)
    return stood_on_table(model["name"], model["V"], model["F"], model["curves"])


def part_names() -> list[str]:
    """The names of every part the corpus has curves for."""
    return [s["name"] for s in groundtruth_loader().MODELS]
