"""histojax uses gymnax's own Environment and spaces classes without importing every gymnax environment
(histojax.core.gymnax_classes), and a later ``import gymnax`` still gives all of gymnax with the same classes."""

import subprocess
import sys

import pytest

pytest.importorskip("gymnax")

HISTOJAX_FIRST = """
import sys
import histojax
assert "gymnax.environments.misc" not in sys.modules, "import histojax ran all of gymnax"
assert "seaborn" not in sys.modules, "import histojax imported seaborn (through gymnax's environments)"
env, params = histojax.make("HistoJAX-Easy-v0")
import gymnax
import gymnax.environments.spaces as spaces_module
from gymnax.environments import environment, spaces
assert isinstance(env, environment.Environment)
assert isinstance(env, gymnax.environments.environment.Environment)
assert isinstance(env.action_space(params), gymnax.environments.spaces.Discrete)
assert spaces_module is spaces is sys.modules["gymnax.environments.spaces"]
cartpole, cp_params = gymnax.make("CartPole-v1")  # the rest of gymnax works, with the same classes
assert type(cartpole.action_space(cp_params)) is spaces.Discrete
assert isinstance(cartpole, environment.Environment)
print("ok")
"""

GYMNAX_FIRST = """
import gymnax
from gymnax.environments import environment, spaces
import histojax
env, params = histojax.make("HistoJAX-Easy-v0")
assert isinstance(env, environment.Environment)
assert type(env.action_space(params)) is spaces.Discrete
print("ok")
"""


@pytest.mark.parametrize("script", [HISTOJAX_FIRST, GYMNAX_FIRST], ids=["histojax-first", "gymnax-first"])
def test_gymnax_classes_are_gymnax_own(script):
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
