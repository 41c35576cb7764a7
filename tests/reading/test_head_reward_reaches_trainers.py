"""``train_readers`` trains with the head reward by wrapping the env every trainer makes: the ``make_env`` each
trainer module (and the evaluation roll-out) imports by name from ``baselines.common.env``. Cheap: no env is made."""

from __future__ import annotations

import ast
import importlib
import pathlib

from baselines.common import env as common_env
from baselines.reading.train_readers import ENV_MAKERS, with_head_reward

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_every_trainer_makes_its_env_through_the_head_reward_until_restored():
    modules = [importlib.import_module(name) for name in ENV_MAKERS]
    restore = with_head_reward(head=object(), gain=None, final=0.0, read_cost=0.0)
    try:
        wrapped = {module.make_env for module in modules}
        assert len(wrapped) == 1 and common_env.make_env not in wrapped
    finally:
        restore()
    assert all(module.make_env is common_env.make_env for module in modules)


def test_every_module_that_imports_make_env_by_name_is_wrapped():
    """A new trainer importing ``make_env`` by name would train without the head reward unless listed."""
    importers = set()
    for path in (ROOT / "baselines").rglob("*.py"):
        for node in ast.parse(path.read_text(), str(path)).body:  # module-level imports: the name a trainer calls
            if (
                isinstance(node, ast.ImportFrom)
                and node.module == "baselines.common.env"
                and any(a.name == "make_env" for a in node.names)
            ):
                importers.add(".".join(path.relative_to(ROOT).with_suffix("").parts))
    assert importers == set(ENV_MAKERS)
