"""gymnax's ``Environment`` base class and its spaces, without importing every gymnax environment.

``import gymnax`` runs ``gymnax/environments/__init__.py``, which imports all of gymnax's own
environments and, through them, seaborn and scipy.stats: about 2 s of every process's start on a
2-core CPU, paid by each ``histojax`` command. histojax needs two of gymnax's modules,
``gymnax.environments.environment`` (the base class of :class:`histojax.core.env.HistoEnv`) and
``gymnax.environments.spaces``; neither imports anything else of gymnax.

:func:`load` executes those two files under their own module names and registers them in
``sys.modules``. The packages above them (``gymnax``, ``gymnax.environments``) are registered as
lazy modules (:class:`importlib.util.LazyLoader`, the standard library's lazy import) that hold
these submodules as attributes and run their real ``__init__`` on first use. So a later
``import gymnax`` gives the whole of gymnax, with the *same* class objects: ``isinstance(env,
gymnax.environments.environment.Environment)`` and ``isinstance(space,
gymnax.environments.spaces.Discrete)`` answer as before, and gymnax's own environments and
wrappers share the classes. When gymnax was imported before histojax, the modules already there
are used unchanged.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
from types import ModuleType

_PACKAGE = "gymnax"
_ENVIRONMENTS = "gymnax.environments"


def _lazy_package(name: str, path: list[str] | None = None) -> tuple[ModuleType, list[str]]:
    """``name`` (a package found on ``path``, default ``sys.path``) in ``sys.modules`` as a lazy module
    whose ``__init__`` runs on first attribute use, and the folders of its submodules (read from its
    spec here: any attribute read on the lazy module would run its ``__init__``)."""
    if name in sys.modules and sys.modules[name] is None:  # Python's mark for "not importable"
        raise ImportError(f"import of {name!r} halted; None in sys.modules")
    spec = importlib.machinery.PathFinder.find_spec(name, path)  # touches no parent module
    if spec is None or spec.loader is None or spec.submodule_search_locations is None:
        raise ImportError(f"no package named {name!r}")  # gymnax is not installed
    locations = list(spec.submodule_search_locations)
    if name in sys.modules:
        return sys.modules[name], locations
    spec.loader = importlib.util.LazyLoader(spec.loader)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)  # a LazyLoader only arms the module here
    return module, locations


def _submodule_file(parent: ModuleType, locations: list[str], name: str) -> ModuleType:
    """Execute the file of submodule ``name`` of ``parent`` (a package whose ``__init__`` may not have
    run; its submodules in the folders ``locations``) under its full name, registered in
    ``sys.modules`` and as ``parent``'s attribute."""
    if name in sys.modules:
        return sys.modules[name]
    short = name.rpartition(".")[2]
    spec = importlib.machinery.PathFinder.find_spec(name, locations)  # the file in locations; no parent runs
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {name!r} from {locations}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    setattr(parent, short, module)  # setting an attribute does not trigger a lazy module's load
    return module


def load(name: str) -> ModuleType:
    """The module ``gymnax.environments.<name>`` (``"environment"`` or ``"spaces"``), loaded without
    running gymnax's package ``__init__`` files (see the module docstring).

    Raises :class:`ImportError` when gymnax is not installed.
    """
    full = f"{_ENVIRONMENTS}.{name}"
    if full in sys.modules:
        return sys.modules[full]
    if type(sys.modules.get(_PACKAGE)) is ModuleType:
        return importlib.import_module(full)  # gymnax already imported in full (not lazily): use it
    package, package_locations = _lazy_package(_PACKAGE)
    environments, locations = _lazy_package(_ENVIRONMENTS, package_locations)
    setattr(package, "environments", environments)
    return _submodule_file(environments, locations, full)
