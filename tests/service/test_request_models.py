"""The request models with the core's parameters are made at run time from the core's
declarations (recon.params), and declared field by field for type checkers and readers
(``if TYPE_CHECKING:`` in service/schemas.py). The two must agree: names, types, defaults and
which are required."""

import ast
import typing
from pathlib import Path

import pytest
from pydantic_core import PydanticUndefined

from service import schemas

SCHEMAS = Path(schemas.__file__)


def _static_declarations() -> dict[str, dict[str, tuple[str, ast.expr | None]]]:
    """The classes declared under ``if TYPE_CHECKING:``: field -> (annotation source, default)."""
    tree = ast.parse(SCHEMAS.read_text())
    found = {}
    for node in tree.body:
        if (
            isinstance(node, ast.If)
            and isinstance(node.test, ast.Name)
            and node.test.id == "TYPE_CHECKING"
        ):
            for cls in node.body:
                if isinstance(cls, ast.ClassDef):
                    found[cls.name] = {
                        item.target.id: (ast.unparse(item.annotation), item.value)
                        for item in cls.body
                        if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
                    }
    return found


def _plain(hint):
    """A field's annotation without pydantic's bounds (Annotated metadata), to compare types."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Annotated:
        return _plain(args[0])
    if origin is None or not args:
        return hint
    if origin is typing.Literal:
        return hint
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return typing.Union[tuple(_plain(a) for a in args)]  # noqa: UP007
    return origin[tuple(_plain(a) for a in args)]


@pytest.mark.parametrize(
    "name, model, base",
    [
        ("ReconstructionCreate", schemas.ReconstructionCreate, schemas._ReconstructionRequest),
        ("TrajectoryCreate", schemas.TrajectoryCreate, schemas._TrajectoryRequest),
    ],
)
def test_the_static_declaration_is_the_generated_model(name, model, base):
    declared = _static_declarations()[name]
    generated = {k: f for k, f in model.model_fields.items() if k not in base.model_fields}
    assert set(declared) == set(generated)
    namespace = vars(schemas)
    for field, (annotation, default) in declared.items():
        info = generated[field]
        # The same type (the generated one carries the core's bounds on top).
        assert _plain(eval(annotation, namespace)) == _plain(info.annotation), field
        if default is None:
            assert info.is_required(), f"{field} is declared required but has a default"
        else:
            assert not info.is_required(), field
            assert info.default is not PydanticUndefined
            assert eval(ast.unparse(default), namespace) == info.default, field


def test_a_generated_field_carries_the_core_s_bounds():
    # What the static declaration cannot show: the bounds come from the core.
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="radius_m"):
        schemas.ReconstructionCreate(radius_m=-1.0)
    with pytest.raises(ValidationError, match="speed_m_s"):
        schemas.TrajectoryCreate(reconstruction_id="rec_1")
