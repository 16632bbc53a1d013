"""Issue 40, items 4-6 (systems, executors, the new surface's raw errors): each case fails loudly with a package
error that names what was expected, what was received and the fix."""

from __future__ import annotations

import concurrent.futures
import functools
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchmisspec as tms
from torchmisspec.cli import main
from torchmisspec.parallel import map_tasks
from torchmisspec.signals import Controls


# ------------------------------------------------------------------------------------------------------------------
# 4. a control named like a state
def test_a_control_named_like_a_state_is_refused_where_the_system_is_built():
    with pytest.raises(tms.InputError, match=r"state and control names must be distinct.*'X'"):
        tms.MisspecifiedSystem(
            lambda t, y, u: -y,
            2,
            num_controls=1,
            control_names=["X"],
            state_names=["X", "S"],
            correction_inputs=["X"],
        )
    # distinct names are fine, and the name resolves to the control
    system = tms.MisspecifiedSystem(
        lambda t, y, u: -y, 2, num_controls=1, control_names=["D"], state_names=["X", "S"], correction_inputs=["D"]
    )
    assert system.correction_inputs == (2,)


# ------------------------------------------------------------------------------------------------------------------
# 5. executors that return the wrong number of results, or that were shut down
class _Dropping(concurrent.futures.Executor):
    """Runs the tasks but its map loses the last result."""

    def map(self, fn, *iterables, **kwargs):
        return list(map(fn, *iterables))[:-1]


class _Doubling(concurrent.futures.Executor):
    """Its map gives the first result twice."""

    def map(self, fn, *iterables, **kwargs):
        out = list(map(fn, *iterables))
        return out[:1] + out


def _shut_down() -> concurrent.futures.ThreadPoolExecutor:
    pool = concurrent.futures.ThreadPoolExecutor(1)
    pool.shutdown()
    return pool


def _square(x: int) -> int:
    return x * x


def _fails(x: int) -> int:
    raise tms.IntegrationError(f"task {x} blew up")


def _calibration_case():
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(5)
    times = torch.linspace(0.0, 6.0, 11, dtype=torch.float64)
    y0 = tms.design.candidates.uniform_box(6, system.domain, generator=g)
    clean = tms.simulate(system, y0, times)
    data = tms.Trajectories(times, clean.states * (1 + 0.003 * torch.randn(clean.states.shape, generator=g)))
    samples = tms.correction_samples(data, system)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4).fit(samples)
    return tms.CorrectedODE(system, gp), data, samples


def _design_case():
    from torchmisspec.benchmarks.default_fit import predator_prey  # a nonlinear G: its proxies go through map_tasks

    system = predator_prey()
    candidates = tms.design.candidates.uniform_box(12, system.domain, generator=torch.Generator().manual_seed(2))
    times = torch.linspace(0.0, 4.0, 6, dtype=torch.float64)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-2, noise_variance=1e-4)
    return system, candidates, times, gp


def _entry_points():
    """The four ways an executor is used: name -> call(executor)."""
    model, data, samples = _calibration_case()
    system, candidates, times, gp = _design_case()
    options = dict(folds=3, num_samples=10, refit=False, progress=False)
    return {
        "map_tasks": lambda ex: map_tasks(_square, range(3), ex),
        "calibrate_bands": lambda ex: tms.calibrate_bands(model, data, samples, executor=ex, **options),
        "greedy": lambda ex: tms.design.greedy(candidates, 2, system=system, times=times, gp=gp, executor=ex),
        "Campaign": lambda ex: tms.design.Campaign(system, candidates, times, gp, executor=ex).ask(2),
    }


@pytest.fixture(scope="module")
def entry_points():
    return _entry_points()


@pytest.mark.parametrize("name", ["map_tasks", "calibrate_bands", "greedy", "Campaign"])
def test_an_executor_that_loses_results_is_refused(entry_points, name):
    with pytest.raises(tms.InputError, match=r"expected \d+ results? \(one per task\).* got \d+ .*_Dropping"):
        entry_points[name](_Dropping())
    with pytest.raises(tms.InputError, match=r"expected \d+ results? \(one per task\).* got more than \d+ .*_Doubling"):
        entry_points[name](_Doubling())


@pytest.mark.parametrize("name", ["map_tasks", "calibrate_bands", "greedy", "Campaign"])
def test_a_shut_down_executor_is_refused_with_the_fix(entry_points, name):
    with pytest.raises(tms.InputError, match=r"ThreadPoolExecutor.*shut down.*pass a running executor, or None"):
        entry_points[name](_shut_down())


def test_the_tasks_own_errors_pass_through_an_executor_unchanged():
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        with pytest.raises(tms.IntegrationError, match="task 0 blew up"):
            map_tasks(_fails, range(3), pool)
    with pytest.raises(tms.IntegrationError, match="task 0 blew up"):
        map_tasks(_fails, range(3), _Dropping())  # an executor whose map runs the tasks at once


def test_an_executor_whose_map_returns_no_iterable_is_refused():
    class _Nothing(concurrent.futures.Executor):
        def map(self, fn, *iterables, **kwargs):
            return None

    with pytest.raises(tms.InputError, match=r"expected .*an iterable of results.*got NoneType.*_Nothing"):
        map_tasks(_square, range(3), _Nothing())


# ------------------------------------------------------------------------------------------------------------------
# 6. G's arity, checked where the system is built
class _Decay(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.rate = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))

    def forward(self, y):
        return -self.rate * y


def _three(t, y, u):
    return -y


@pytest.mark.parametrize(
    ("known", "kwargs", "expected"),
    [
        (lambda t, y, u: -y, {}, r"G\(y\)"),
        (lambda y: -y, {"parameters": {"a": (1.0, 0.1)}}, r"G\(y, theta\)"),
        (lambda y: -y, {"num_controls": 1}, r"G\(t, y, u\)"),
        (lambda t, y, u: -y, {"time_dependent": True, "parameters": {"a": (1.0, 0.1)}}, r"G\(t, y, u, theta\)"),
        (lambda: 0, {}, r"G\(y\)"),
        (_Decay(), {"num_controls": 1}, r"G\(t, y, u\)"),
    ],
)
def test_a_known_model_of_the_wrong_arity_is_refused_where_the_system_is_built(known, kwargs, expected):
    with pytest.raises(tms.InputError, match=rf"known: expected .*{expected}.* got a callable taking \("):
        tms.MisspecifiedSystem(known, 2, **kwargs)


def test_a_known_model_of_the_right_form_is_accepted():
    def star(*args):
        return -args[-1] if len(args) == 1 else -args[1]

    def defaulted(y, theta=None, scale=1.0):
        return -y

    y, u = torch.ones(3, 2, dtype=torch.float64), torch.zeros(3, 1, dtype=torch.float64)
    for known, kwargs in [
        (star, {}),
        (star, {"num_controls": 1}),
        (defaulted, {}),
        (defaulted, {"parameters": {"a": (1.0, 0.1)}}),
        (functools.partial(_three, 0.0, u=None), {}),  # a partial that leaves G(y)
        (_Decay(), {}),  # an nn.Module: its forward's signature
        (torch.neg, {}),  # a builtin whose signature cannot be read: not checked
    ]:
        system = tms.MisspecifiedSystem(known, 2, **kwargs)
        out = system.known_rhs(y, 0.0, u) if kwargs.get("num_controls") else system.known_rhs(y)
        torch.testing.assert_close(out, -y)
    with pytest.raises(tms.InputError, match=r"expected .*G\(y\).* got a callable taking \(y, u\)"):
        tms.MisspecifiedSystem(functools.partial(_three, 0.0), 2)  # binds t only: it still needs u


def test_a_system_file_with_a_known_model_of_the_wrong_arity_is_refused_when_loaded(tmp_path):
    module = tmp_path / "wrong_arity.py"
    module.write_text(
        "import torchmisspec as tms\n\ndef system():\n    return tms.MisspecifiedSystem(lambda t, y, u: -y, 2)\n"
    )
    with pytest.raises(
        tms.InputError, match=r"wrong_arity.py:system.*expected a callable G\(y\).* got a callable taking"
    ):
        tms.systems.load_system(f"{module}:system")


# ------------------------------------------------------------------------------------------------------------------
# 6. errors raised inside the user's G
def _simulate(system):
    return tms.simulate(system, torch.ones(2, 2, dtype=torch.float64), torch.linspace(0.0, 1.0, 5))


def test_an_exception_inside_g_names_the_users_file_and_line():
    def known(y):
        return undefined_rate * y  # noqa: F821 - the user's bug

    line = known.__code__.co_firstlineno + 1
    with pytest.raises(tms.InputError, match=rf"G raised NameError: .*undefined_rate.*test_issue40_systems.py:{line}"):
        _simulate(tms.MisspecifiedSystem(known, 2))


def test_a_value_error_inside_g_during_a_solve_is_not_a_solver_settings_error():
    calls = [0]

    def known(y):
        calls[0] += 1
        if calls[0] > 4:
            raise ValueError("the user's own check failed")
        return -y

    with pytest.raises(tms.InputError, match=r"G raised ValueError: the user's own check failed.*test_issue40") as info:
        _simulate(tms.MisspecifiedSystem(known, 2))
    assert "solver settings" not in str(info.value)


def test_g_returning_the_wrong_shape_partway_through_a_solve_is_a_shape_error_of_g():
    calls = [0]

    def known(y):
        calls[0] += 1
        return -y if calls[0] < 5 else -y[..., :1]

    with pytest.raises(tms.ShapeError, match=r"G returned shape \(2, 1\) .*expected \(2, 2\)") as info:
        _simulate(tms.MisspecifiedSystem(known, 2))
    assert "solver settings" not in str(info.value)


def test_a_bad_solver_option_is_still_reported_as_a_solver_setting():
    system = tms.systems.paper_linear()
    with pytest.raises(tms.InputError, match="expected solver settings torchdiffeq accepts"):
        tms.simulate(system, torch.ones(1, 2), torch.linspace(0.0, 1.0, 3), method="no_such_method")


@pytest.fixture
def observed_csv(tmp_path):
    y0 = torch.rand(3, 2, generator=torch.Generator().manual_seed(7), dtype=torch.float64) * 2 - 1
    trajs = tms.simulate(tms.systems.paper_linear(), y0, torch.linspace(0, 6, 11, dtype=torch.float64))
    return trajs.save(tmp_path / "obs.csv", time_column="t", state_columns=["x1", "x2"])


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            "    return rate * y\n",
            r"G raised NameError: name 'rate' is not defined \(at .*buggy_model.py:4, in known\)",
        ),
        (
            "    return -y if y.shape[0] < 0 else y.reshape(7, 7)\n",
            r"G raised RuntimeError: .*shape '\[7, 7\]'.* \(at .*buggy_model.py:4, in known\)",
        ),
    ],
)
def test_the_cli_reports_an_error_in_the_users_g_with_its_file_and_line(tmp_path, observed_csv, capsys, body, message):
    module = tmp_path / "buggy_model.py"
    module.write_text(
        "import torchmisspec as tms\n\n"
        "def known(y):\n"
        f"{body}\n"
        "def system():\n"
        "    return tms.MisspecifiedSystem(known, 2, name='buggy')\n"
    )
    out = tmp_path / "m.pt"
    args = ["fit", "--data", str(observed_csv), "--system", f"{module}:system", "--time-column", "t"]
    assert main([*args, "--out", str(out), "--quiet", "--derivative", "central", "--no-calibrate"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchmisspec fit: error: ") and "\n" not in err and "internal error" not in err
    assert __import__("re").search(message, err), err
    assert not out.exists()
    sys.modules.pop("buggy_model", None)


# ------------------------------------------------------------------------------------------------------------------
# 6. Controls' sizes
@pytest.fixture
def controls():
    return Controls(torch.tensor([0.0, 1.0], dtype=torch.float64), torch.ones(2, 2, 1, dtype=torch.float64))


@pytest.mark.parametrize(("n", "got"), [(0, "got 0"), (-1, "got -1"), (1.5, "got 1.5"), (True, "got True")])
def test_controls_repeat_checks_its_count(controls, n, got):
    with pytest.raises(tms.InputError, match=rf"n: expected an integer >= 1, {got}"):
        controls.repeat(n)


def test_controls_repeat_keeps_the_profiles(controls):
    twice = controls.repeat(2)
    assert twice.num_experiments == 4 and "K=4" in repr(twice)


@pytest.mark.parametrize(
    ("experiments", "count", "message"),
    [
        (2, -1, "num_controls: expected an integer >= 1, got -1"),
        (2, 0, "num_controls: expected an integer >= 1, got 0"),
        (0, 1, "num_experiments: expected an integer >= 1, got 0"),
        (2.0, 1, r"num_experiments: expected an integer >= 1, got 2.0"),
    ],
)
def test_controls_from_function_checks_its_sizes(experiments, count, message):
    with pytest.raises(tms.InputError, match=message):
        Controls.from_function(lambda t: t[..., None], experiments, count)


# ------------------------------------------------------------------------------------------------------------------
# 6. correction_error without a model; oracle targets of an nn.Module G
@pytest.mark.parametrize("gp", [None, "model.pt", np.zeros(3)])
def test_correction_error_refuses_something_that_is_not_a_model(gp):
    with pytest.raises(tms.InputError, match=r"gp: expected a fitted torchmisspec.CorrectionGP .*got"):
        tms.metrics.correction_error(gp, tms.systems.paper_linear())


def test_oracle_targets_of_a_trainable_g_carry_no_graph():
    system = tms.MisspecifiedSystem(_Decay(), 2, correction=lambda y: 0.01 * y**2)
    data = tms.simulate(system, torch.ones(2, 2, dtype=torch.float64), torch.linspace(0.0, 1.0, 5))
    samples = tms.correction_samples(data, system, derivative="oracle")
    assert not samples.targets.requires_grad and samples.targets.grad_fn is None


# ------------------------------------------------------------------------------------------------------------------
# Properties over the classes above (hypothesis): every case is accepted with the right result, or refused with a
# package error; never a raw exception, never a silently wrong count.


class _Giving(concurrent.futures.Executor):
    """Its map gives the results of the tasks with ``extra`` more (> 0: the first repeated) or fewer (< 0)."""

    def __init__(self, extra: int) -> None:
        self.extra = extra

    def map(self, fn, *iterables, **kwargs):
        out = list(map(fn, *iterables))
        return out[: len(out) + self.extra] if self.extra < 0 else out + out[:1] * self.extra


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 8), st.integers(-3, 3))
def test_map_tasks_gives_one_result_per_task_or_refuses(n, extra):
    executor = _Giving(extra)
    if extra == 0 or n == 0:  # nothing to repeat or to drop: the right count
        assert map_tasks(_square, range(n), executor) == [x * x for x in range(n)]
        return
    with pytest.raises(tms.InputError, match=rf"expected {n} results? \(one per task\)"):
        map_tasks(_square, range(n), executor)


def _with_arity(count: int, star: bool = False):
    import inspect

    def known(*args):
        return -args[1] if len(args) >= 3 else -args[0]

    kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
    parameters = [inspect.Parameter(f"a{i}", kind) for i in range(count)]
    if star:
        parameters.append(inspect.Parameter("rest", inspect.Parameter.VAR_POSITIONAL))
    known.__signature__ = inspect.Signature(parameters)
    return known


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 5), st.booleans(), st.booleans(), st.booleans(), st.booleans())
def test_a_known_model_is_accepted_exactly_when_its_arity_fits(count, controls, timed, theta, star):
    expected = (1 if not (controls or timed) else 3) + (1 if theta else 0)
    kwargs = {"num_controls": int(controls), "time_dependent": timed}
    if theta:
        kwargs["parameters"] = {"a": (1.0, 0.1)}
    known = _with_arity(count, star)
    if count == expected or (star and count <= expected):
        tms.MisspecifiedSystem(known, 1, **kwargs)
    else:
        with pytest.raises(tms.InputError, match=r"known: expected a callable G\((t, y, u|y)(, theta)?\)"):
            tms.MisspecifiedSystem(known, 1, **kwargs)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from("XSDPQ"), min_size=1, max_size=3, unique=True), st.sampled_from("XSDPQ"))
def test_a_system_is_built_exactly_when_its_state_and_control_names_differ(states, control):
    build = functools.partial(
        tms.MisspecifiedSystem, lambda t, y, u: -y, len(states), num_controls=1, control_names=[control],
        state_names=states,
    )  # fmt: skip
    if control in states:
        with pytest.raises(tms.InputError, match="state and control names must be distinct"):
            build()
    else:
        system = build()
        assert system.state_names == tuple(states) and system.control_names == (control,)


@settings(max_examples=60, deadline=None)
@given(st.one_of(st.integers(-3, 4), st.floats(-2, 4), st.booleans(), st.none(), st.text(max_size=2)))
def test_controls_repeat_gives_n_times_the_profiles_or_refuses(n):
    controls = Controls(torch.tensor([0.0, 1.0], dtype=torch.float64), torch.ones(2, 2, 1, dtype=torch.float64))
    if isinstance(n, int) and not isinstance(n, bool) and n >= 1:
        repeated = controls.repeat(n)
        assert repeated.num_experiments == 2 * n and f"K={2 * n}" in repr(repeated)
    else:
        with pytest.raises(tms.InputError, match="n: expected an integer >= 1"):
            controls.repeat(n)


def test_controls_named_otherwise_than_the_system_are_refused():
    """Controls named (D, T) for a system whose controls are (T, D) were read by position."""
    system = tms.MisspecifiedSystem(
        lambda t, y, u: -u[..., :1] * y, 1, num_controls=2, control_names=["T", "D"], state_names=["x"]
    )
    knots = torch.tensor([0.0], dtype=torch.float64)
    swapped = tms.Controls(knots, torch.tensor([[[0.1, 0.5]]], dtype=torch.float64), names=["D", "T"])
    data = tms.Trajectories(torch.linspace(0, 1, 5, dtype=torch.float64), torch.ones(1, 5, 1), controls=swapped)
    with pytest.raises(tms.InputError, match=r"expected the controls of system .*\['T', 'D'\].*got \['D', 'T'\]"):
        tms.correction_samples(data, system, derivative="central")
    unnamed = tms.Controls(knots, torch.tensor([[[0.1, 0.5]]], dtype=torch.float64))  # u0, u1: by position
    by_position = tms.Trajectories(data.times, data.states, controls=unnamed)
    samples = tms.correction_samples(by_position, system, derivative="central")
    assert samples.inputs.shape[0] == 5
