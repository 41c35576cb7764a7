"""The mode names ``make`` takes are one registry in the env core (``histojax.core.modes.factory``): the core
registers its navigation and observation modes, the reading stack adds ``glimpse`` and ``zoom_select`` (and the
coarse map's builder) when it is imported, so the core never imports ``histojax.reading``. No env is made here."""

import ast
import dataclasses
import inspect

import pytest

import histojax  # noqa: F401  (imports the reading stack, which registers its modes)
from histojax.core import seen_views
from histojax.core.modes import base, factory
from histojax.reading.modes.glimpse import Glimpse
from histojax.reading.modes.zoom_select import ZoomSelect


def _imports(module) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(inspect.getsource(module))):
        if isinstance(node, ast.ImportFrom):
            out.add(node.module or "")
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return out


def test_the_reading_modes_are_registered_by_the_reading_stack():
    assert not {m for m in _imports(factory) | _imports(base) if m.startswith("histojax.reading")}
    assert list(factory.ACTION_MODES)[:2] == ["discrete", "continuous"]
    assert {"glimpse", "zoom_select"} <= set(factory.ACTION_MODES)
    assert factory.action_mode("glimpse") == Glimpse() and factory.action_mode("glimpse:2") == Glimpse(level=2)
    assert factory.action_mode("zoom_select:4") == ZoomSelect(k=4)
    assert factory.action_mode("discrete:map") == base.Discrete(memory=True, coarse_map=True)
    assert factory.action_mode("continuous:memory") == base.Continuous(memory=True)


@pytest.mark.parametrize(
    "name, message",
    [
        ("glimpse:x", "the part after ':' must be a whole number"),
        ("discrete:x", "action_mode must be one of ('discrete', 'continuous', 'glimpse', 'zoom_select'"),
        ("discrete:", "glimpse:LEVEL, zoom_select:K"),
        ("nothing", "discrete:memory, continuous:memory, discrete:map, continuous:map"),
    ],
)
def test_a_wrong_mode_name_is_one_line(name, message):
    with pytest.raises(ValueError) as e:
        factory.action_mode(name)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_a_mode_of_your_own_is_registered_the_same_way(monkeypatch):
    @dataclasses.dataclass(frozen=True)
    class Still(base.Discrete):
        name = "still"
        stride: int = 1

    monkeypatch.setattr(factory, "ACTION_MODES", dict(factory.ACTION_MODES))
    monkeypatch.setattr(factory, "ACTION_FORMS", list(factory.ACTION_FORMS))
    factory.register_action_mode("still", factory.whole_number_arg(Still, "stride", "still"), ("still:N",))
    assert factory.action_mode("still:3") == Still(stride=3)
    with pytest.raises(ValueError, match="still:N"):
        factory.action_mode("nothing")


def test_a_coarse_map_without_its_builder_is_one_line(monkeypatch):
    monkeypatch.setattr(seen_views, "_COARSE_MAP_BUILDER", [])
    with pytest.raises(ValueError, match="built by the reading stack") as e:
        seen_views.coarse_maps(None, None, (), 62)
    assert "\n" not in str(e.value)
