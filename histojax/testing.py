"""The environment contract, as a check users can run (like Jumanji's ``testing`` kit).

    from histojax.testing import check_env
    env, params = histojax.make("HistoJAX-Easy-v0")
    report = check_env(env, params)       # every check's name, result and detail
    assert report.ok, report.failures

or, for every registered id (the ``make contract`` target)::

    histojax contract                     # also: python -m histojax.testing

What is checked, for one env and its params (what a user of gymnax-style code relies on):
  * ``EnvState`` has ``z``, ``x``, ``y``, ``t``; ``reset`` gives an observation inside
    ``env.observation_space(params)`` and ``step`` a 6-tuple ``(obs, state, reward, terminated,
    truncated, info)``; a discrete detection env has 7 actions (HistoGym's);
  * zooming in from the start visits exactly ``env.n_levels`` levels and zooming out returns to the
    start level (for the action modes whose zoom action is known: discrete and continuous);
  * ``jax.vmap`` over ``batch`` envs inside ``jax.lax.scan`` over ``steps`` random actions runs under
    ``jax.jit``: finite rewards, positions inside ``[0, level size − tile_size]``, observations
    inside the space;
  * the same key gives the same trajectory, jitted or not (``jit_steps`` steps), and twice jitted.

Each configuration compiles ``reset`` / ``step`` once and the batched scan once; budgets are small.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np

from data_tools.cli_output import command_main
from histojax.core import actions


@dataclasses.dataclass
class ContractReport:
    """The results of :func:`check_env`: ``checks`` is a list of ``(name, passed, detail)``."""

    label: str
    checks: list = dataclasses.field(default_factory=list)
    skipped: str | None = None  # why the env could not be checked here (e.g. a dataset id without its data)

    def check(self, name: str, passed, detail: str = "") -> bool:
        """Record one check; returns whether it passed."""
        passed = bool(passed)
        self.checks.append((f"{self.label} {name}", passed, "" if passed else detail))
        return passed

    @property
    def ok(self) -> bool:
        """True when every check passed."""
        return all(p for _, p, _ in self.checks)

    @property
    def failures(self) -> list[str]:
        """``"name: detail"`` of every failed check."""
        return [f"{n}: {d}" for n, p, d in self.checks if not p]


def zoom_action(env, direction: int):
    """The action that zooms in (``direction=+1``) or out (``-1``) without moving, or ``None`` for an
    action mode whose zoom action this kit does not know."""
    if env.action_mode == "discrete":
        return jnp.int32(actions.ZOOM_IN if direction > 0 else actions.ZOOM_OUT)
    if env.action_mode == "continuous":
        return jnp.zeros((env.num_actions,), jnp.float32).at[2].set(float(direction))
    return None


def _contains(space, obs) -> bool:
    """``obs`` inside ``space`` with its shape and dtype (a dict member by member)."""
    if hasattr(space, "spaces"):
        return (
            isinstance(obs, dict)
            and set(obs) == set(space.spaces)
            and all(_contains(space.spaces[k], obs[k]) for k in obs)
        )
    obs = jnp.asarray(obs)
    return (
        tuple(obs.shape) == tuple(space.shape)
        and jnp.dtype(obs.dtype) == jnp.dtype(space.dtype)
        and bool(space.contains(obs))
    )


def _same(a, b) -> bool:
    return all(bool(jnp.all(x == y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def check_env(
    env, params=None, *, batch: int = 16, steps: int = 32, jit_steps: int = 5, seed: int = 0, label: str | None = None
) -> ContractReport:
    """Check ``env`` (with ``params``, default ``env.default_params``) against the contract in the module
    doc; ``batch`` envs × ``steps`` random steps in the scan, ``jit_steps`` steps compared with
    ``jax.disable_jit``. Returns a :class:`ContractReport` (it raises nothing on a failed check)."""
    params = env.default_params if params is None else params
    report = ContractReport(label or env.name)
    key = jax.random.PRNGKey(seed)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    obs, state = reset(key, params)
    obs_space, act_space = env.observation_space(params), env.action_space(params)
    for f in ("z", "x", "y", "t"):
        report.check(f"state.{f}", hasattr(state, f), "EnvState lacks field")
    if env.action_mode == "discrete" and env.task == "detection":
        report.check("7 actions", getattr(act_space, "n", None) == 7, f"n={getattr(act_space, 'n', None)}")
    report.check(
        "reset obs in space",
        _contains(obs_space, obs),
        f"obs={jax.tree.map(lambda a: (a.shape, a.dtype), obs)} space={obs_space}",
    )
    out = step(key, state, act_space.sample(key), params)
    report.check(
        "6-tuple step",
        isinstance(out, tuple) and len(out) == 6,
        f"len={len(out) if isinstance(out, tuple) else type(out)}",
    )

    zoom_in, zoom_out = zoom_action(env, +1), zoom_action(env, -1)
    if zoom_in is not None:
        zs, s = [int(state.z)], state
        for i in range(env.n_levels + 2):
            _, s2, _, term, trunc, _ = step(jax.random.fold_in(key, i), s, zoom_in, params)
            if bool(term):  # success ends an episode only at the finest level
                zs.append(max(zs) + 1)
                break
            if bool(trunc):
                break
            s = s2
            zs.append(int(s.z))
        report.check(f"{env.n_levels} levels", len(set(zs)) == env.n_levels, f"zoom-in visited z={sorted(set(zs))}")
        for i in range(env.n_levels + 2):
            _, s, *_ = step(jax.random.fold_in(key, 100 + i), s, zoom_out, params)
        report.check("zoom out to start level", int(s.z) == min(zs), f"z={int(s.z)} start={min(zs)}")

    def body(st, k):
        ka, ks = jax.random.split(k)
        acts = jax.vmap(act_space.sample)(jax.random.split(ka, batch))
        o, st, r, te, tr, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(ks, batch), st, acts, params
        )
        inside = jax.vmap(lambda x: jnp.asarray(obs_space.contains(x)))(o)
        return st, (r, st.z, st.x, st.y, inside)

    try:
        _, st_b = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, batch), params)
        _, (rs, zb, xb, yb, inside) = jax.jit(lambda s, ks: jax.lax.scan(body, s, ks))(
            st_b, jax.random.split(key, steps)
        )
        slide = params.slide
        widths, heights = np.asarray(slide.level_width), np.asarray(slide.level_height)
        if widths.ndim == 2:  # a dataset: the largest slide's bounds
            widths, heights = widths.max(axis=0), heights.max(axis=0)
        zb, xb, yb = np.asarray(zb), np.asarray(xb), np.asarray(yb)
        report.check("vmap+scan finite rewards", bool(jnp.all(jnp.isfinite(rs))), "non-finite reward")
        report.check(
            "positions inside the level",
            bool(
                (xb >= 0).all()
                and (yb >= 0).all()
                and (xb <= widths[zb] - env.tile_size).all()
                and (yb <= heights[zb] - env.tile_size).all()
            ),
            "x/y outside [0, level size - tile_size]",
        )
        report.check("vmap+scan obs in space", bool(jnp.all(inside)), "an observation left the space")
    except Exception as e:  # noqa: BLE001  (a crash is a failed check, reported with its cause)
        report.check("vmap+scan", False, repr(e)[:200])

    s_j = s_n = s_k = state
    same = True
    for i in range(jit_steps):
        k = jax.random.fold_in(key, 1000 + i)
        a = act_space.sample(k)
        oj, s_j, rj, *_ = step(k, s_j, a, params)
        ok, s_k, rk, *_ = step(k, s_k, a, params)
        with jax.disable_jit():
            on, s_n, rn, *_ = env.step(k, s_n, a, params)
        same &= bool(jnp.allclose(rj, rn)) and _same(s_j, s_n) and _same(oj, on) and _same((oj, s_j), (ok, s_k))
    report.check("jit == no-jit, same key same trajectory", same, "trajectories differ")
    return report


def check_contract(env_ids: Iterable[str] | None = None, **check_kwargs) -> list[ContractReport]:
    """:func:`check_env` for each of ``env_ids`` (default: every registered id) made with its defaults. An
    id whose data is missing here (``make`` raises a bad-input error, e.g. a C16 id without its dataset) is
    reported as skipped with the reason; any other error making it is a failed check."""
    import histojax
    from data_tools.errors import HistojaxDataError

    reports = []
    for env_id in histojax.registered_envs() if env_ids is None else env_ids:
        try:
            env, params = histojax.make(env_id)
        except HistojaxDataError as e:  # its data is not on this machine (e.g. the C16 dataset): said, not failed
            reports.append(ContractReport(env_id, skipped=str(e).splitlines()[0][:300]))
            continue
        except Exception as e:  # noqa: BLE001
            report = ContractReport(env_id)
            report.check("make", False, str(e).splitlines()[0][:300])
            reports.append(report)
            continue
        reports.append(check_env(env, params, **check_kwargs))
    return reports


def add_arguments(p) -> None:
    """The options of ``histojax contract`` and ``python -m histojax.testing``: env ids."""
    p.add_argument("env_ids", nargs="*", help="registered ids (default: all)")


def run(args, parser=None) -> int:
    """Print one line per failed check and, last, ``contract: passed/total``; exit 0 only if all pass."""
    reports = check_contract(args.env_ids or None)
    checks = [c for r in reports for c in r.checks]
    failures = [f for r in reports for f in r.failures]
    for r in reports:
        if r.skipped:
            print(f"SKIP {r.label}: {r.skipped}")
    for f in failures:
        print(f"FAIL {f}")
    print(f"contract: {len(checks) - len(failures)}/{len(checks)}")
    return 0 if not failures else 1


main = command_main(add_arguments, run, "python -m histojax.testing", __doc__)  # = histojax contract


if __name__ == "__main__":
    sys.exit(main())
