"""Property-based (metamorphic) tests of the surface added in 0.2: controls, uncertain parameters, readouts,
partial measurements (NaN states), ragged data, executors, files, saved models, predictions and designs.

Each property relates two computations that must agree (the same data named in another order, split into two calls,
saved and loaded, in other units, in float32): the class of bug issue 40 is about, a confident answer from the wrong
data, shows up as a disagreement. Where the package may refuse instead, the refusal must be a package error whose
message says what was expected and what was received. The one-bad-argument fuzz of the same surface is in
tests/test_fuzz.py. The default run is fast (module-scope fixtures, few examples); ``-m slow`` runs more examples.
"""

from __future__ import annotations

import concurrent.futures
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchmisspec as tms
from torchmisspec.signals import Controls

DT = torch.float64
FAST = settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
LONG = settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))


def refused(exc: BaseException) -> None:
    """A refusal is a package error naming what was expected and what was received."""
    assert isinstance(exc, tms.TorchMisspecError), f"raw {type(exc).__name__}: {exc}"
    text = str(exc)
    assert "expected" in text and ("got" in text or "received" in text), text


def same(a, b, rtol=1e-12, atol=0.0, what=""):
    a, b = torch.as_tensor(a).detach().double(), torch.as_tensor(b).detach().double()
    assert a.shape == b.shape, f"{what}: shapes {tuple(a.shape)} vs {tuple(b.shape)}"
    torch.testing.assert_close(a, b, rtol=rtol, atol=atol, equal_nan=True, msg=what)


def same_trajectories(a: tms.Trajectories, b: tms.Trajectories, *, samples: bool = True) -> None:
    """Every field of two trajectories equal (NaN where NaN); the controls' profiles as the same samples, or (not
    ``samples``: a table holds a profile's samples at every row) as the same functions of time."""
    assert a.state_names == b.state_names and a.lengths == b.lengths and a.is_ragged == b.is_ragged
    same(a.flat_times(), b.flat_times(), rtol=0, what="times")
    same(a.flat_states(), b.flat_states(), rtol=0, what="states")
    assert (a.controls is None) == (b.controls is None)
    if a.controls is not None:
        assert (a.controls.names, a.controls.kind) == (b.controls.names, b.controls.kind)
        if samples:
            for (ka, va), (kb, vb) in zip(a.controls.profiles(), b.controls.profiles(), strict=True):
                same(ka, kb, rtol=0, what="knots")
                same(va, vb, rtol=0, what="control values")
        every = torch.cat([a.flat_times(), a.controls.knots.reshape(-1).to(a.flat_times())]).unique()
        grid = torch.cat([every, (every[:-1] + every[1:]) / 2, every[-1:] + 1]).sort().values
        same(a.controls.at(grid.expand(len(a), -1)), b.controls.at(grid.expand(len(b), -1)), rtol=0, what="u(t)")
    assert (a.readout is None) == (b.readout is None) and (a.readout is None or a.readout == b.readout)
    if a.readings is not None:
        cat = (lambda r: torch.cat(list(r))) if a.is_ragged else (lambda r: r)
        same(cat(a.readings), cat(b.readings), rtol=0, what="readings")
    assert (a.initial_states is None) == (b.initial_states is None)
    if a.initial_states is not None:
        same(a.initial_states, b.initial_states, rtol=0, what="initial states")


# ------------------------------------------------------------------------------------------------------ fixtures
def chemo_known(t, y, u):
    x, s, d = y[..., 0], y[..., 1], u[..., 0]
    return torch.stack([0.8 * x * s - d * x, d * (1.0 - s) - 0.8 * x * s], dim=-1)


def chemostat(**options) -> tms.MisspecifiedSystem:
    """Biomass X on substrate S under a dilution rate D; F on dX/dt depends on X and D."""
    kw = dict(state_names=["X", "S"], num_controls=1, control_names=["D"], name="chemostat",
              correction=lambda x: -0.2 * x[..., :1] * x[..., 1:2], correction_inputs=["X", "D"],
              correction_outputs=["X"])  # fmt: skip
    kw.update(options)
    return tms.MisspecifiedSystem(chemo_known, 2, **kw)


CHEMO = chemostat()
CY0 = torch.tensor([[0.3, 0.6], [0.4, 0.5], [0.2, 0.8], [0.5, 0.3]], dtype=DT)
CTIMES = torch.linspace(0.0, 8.0, 9, dtype=DT)
CKNOTS = torch.tensor([0.0, 3.0, 6.0], dtype=DT)
CVALUES = torch.tensor([[0.1, 0.3, 0.2], [0.25, 0.15, 0.1], [0.3, 0.3, 0.05], [0.2, 0.1, 0.3]], dtype=DT)[..., None]
CCONTROLS = Controls(CKNOTS, CVALUES, names=["D"])
CTRAJ = tms.simulate(CHEMO, CY0, CTIMES, controls=CCONTROLS)
CSAMPLES = tms.correction_samples(CTRAJ, CHEMO, derivative="oracle")
CGP = tms.CorrectionGP(lengthscale=0.5, outputscale=1e-2, noise_variance=1e-6).fit(CSAMPLES.inputs, CSAMPLES.targets)
CMODEL = tms.CorrectedODE(CHEMO, CGP)

THREE_A = torch.tensor([[-0.3, 0.2, 0.0], [0.1, -0.4, 0.2], [0.0, 0.3, -0.2]], dtype=DT)
THREE = tms.MisspecifiedSystem(
    tms.systems.LinearField(THREE_A), 3, correction=lambda y: 0.1 * y**2, state_names=["A", "B", "C"], name="three"
)
THREE_TRAJ = tms.simulate(THREE, torch.tensor([[1.0, 0.5, -0.5], [0.2, -0.8, 0.4], [-0.6, 0.3, 0.9]], dtype=DT),
                          torch.linspace(0.0, 4.0, 11, dtype=DT))  # fmt: skip

LIN = tms.systems.paper_linear()
TIMES = torch.linspace(0.0, 6.0, 7, dtype=DT)
Y0 = torch.tensor([[0.5, -0.3], [0.2, 0.7], [-0.6, 0.1]], dtype=DT)
TRAJ = tms.simulate(LIN, Y0, TIMES)
SAMPLES = tms.correction_samples(TRAJ, LIN, derivative="oracle")
HYPER = dict(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-6)
GP = tms.CorrectionGP(**HYPER).fit(SAMPLES.inputs, SAMPLES.targets)


def oscillator() -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        lambda y, theta: torch.stack([y[..., 1], -y[..., 0] - theta[0] * y[..., 1]], -1), 2, state_names=["x", "v"],
        parameters={"c": (0.4, 0.2)}, correction_inputs=["x"], correction_outputs=[1],
        correction=lambda x: -0.3 * x**3, name="oscillator",
    )  # fmt: skip


names_strategy = st.lists(st.sampled_from(["X", "S", "P", "Q", "biomass", "y0", "y1"]), min_size=2, max_size=2)


# --------------------------------------------------------------------------------- 1. states matched by their names
@FAST
@given(st.permutations([0, 1, 2]))
def test_states_permuted_with_their_names_give_the_same_samples_or_a_refusal(order):
    """The columns of a named system's data in another order, with their names: the same correction samples (read
    by name) or a refusal naming both orders; never the samples of another state."""
    names = [THREE_TRAJ.state_names[j] for j in order]
    shuffled = THREE_TRAJ.reordered(names)
    base = tms.correction_samples(THREE_TRAJ, THREE, derivative="central")
    try:
        got = tms.correction_samples(shuffled, THREE, derivative="central")
    except tms.TorchMisspecError as exc:
        refused(exc)
        assert order != [0, 1, 2] and "reordered" in str(exc)
        return
    same(got.inputs, base.inputs, what="inputs")
    same(got.targets, base.targets, what="targets")


@FAST
@given(st.permutations([0, 1, 2]))
def test_reordered_then_back_is_the_identity(order):
    names = [THREE_TRAJ.state_names[j] for j in order]
    shuffled = THREE_TRAJ.reordered(names)
    for j, name in enumerate(names):
        same(shuffled.states[..., j], THREE_TRAJ.states[..., THREE_TRAJ.state_names.index(name)], rtol=0)
    same_trajectories(shuffled.reordered(THREE_TRAJ.state_names), THREE_TRAJ)


@FAST
@given(st.permutations([0, 1, 2]), st.lists(st.floats(-3, 3).filter(lambda w: abs(w) > 1e-3), min_size=3, max_size=3))
def test_a_readout_over_names_in_any_order_reads_the_same_numbers(order, weights):
    """A readout written over the states' names in any order reads, by name, the same numbers from the data."""
    names = THREE_TRAJ.state_names
    readout = tms.Readout.from_weights({"z": {names[j]: weights[j] for j in order}}, [names[j] for j in order])
    read = THREE_TRAJ.with_readout(readout).readings
    want = sum(weights[j] * THREE_TRAJ.states[..., j : j + 1] for j in range(3))
    same(read, want, rtol=1e-12, atol=1e-14, what="readings by name")
    reordered = THREE_TRAJ.reordered([names[j] for j in order]).with_readout(readout)
    same(reordered.readings, want, rtol=1e-12, atol=1e-14, what="readings of the reordered data")


@FAST
@given(st.permutations(["P", "Q", "R"]))
def test_a_readout_over_other_names_is_refused_not_read_by_position(names):
    readout = tms.Readout.parse(["z = P + 2*Q"], list(names))
    with pytest.raises(tms.InputError) as info:
        THREE_TRAJ.with_readout(readout)
    refused(info.value)


def two_control_system() -> tms.MisspecifiedSystem:
    return tms.MisspecifiedSystem(
        lambda t, y, u: -u[..., :1] * y + u[..., 1:2], 1, state_names=["level"], num_controls=2,
        control_names=["outflow", "inflow"], name="tank",
    )  # fmt: skip


@FAST
@given(st.booleans())
def test_controls_named_in_another_order_give_the_same_path_or_a_refusal(swap):
    """Controls whose names (and values) come in another order than the system's: the same simulation, or a
    refusal; never the outflow read as the inflow."""
    system = two_control_system()
    values = torch.tensor([[[0.5, 1.0], [0.2, 0.3]], [[0.1, 0.4], [0.7, 0.2]]], dtype=DT)
    y0, times = torch.tensor([[1.0], [0.3]], dtype=DT), torch.linspace(0, 4, 9, dtype=DT)
    base = tms.simulate(system, y0, times, controls=Controls([0.0, 2.0], values, names=["outflow", "inflow"]))
    names = ["inflow", "outflow"] if swap else ["outflow", "inflow"]
    given_values = values.flip(-1) if swap else values
    try:
        got = tms.simulate(system, y0, times, controls=Controls([0.0, 2.0], given_values, names=names))
    except tms.TorchMisspecError as exc:
        refused(exc)
        assert swap
        return
    same(got.states, base.states, rtol=1e-9, atol=1e-12, what="the same controls by name")


# ----------------------------------------------------------------------------------------------- 2. file round trips
@st.composite
def trajectories_strategy(draw):
    """Small trajectories with any mix of the 0.2 fields: names, ragged lengths, missing entries, controls (either
    kind), a readout with its readings, initial states, float32."""
    K, d = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    ragged = K > 1 and draw(st.booleans())
    lengths = [draw(st.integers(3, 6)) for _ in range(K)] if ragged else [draw(st.integers(1, 6))] * K
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**16)))
    times = [torch.cumsum(0.1 + torch.rand(n, generator=g, dtype=DT), 0) for n in lengths]
    states = [torch.randn(n, d, generator=g, dtype=DT) for n in lengths]
    if draw(st.booleans()):  # missing entries, never a whole row (a row with nothing observed is dropped)
        for y in states:
            hole = torch.rand(y.shape, generator=g) < 0.25
            hole[:, 0] = False
            y[hole] = float("nan")
    names = draw(st.one_of(st.none(), st.lists(st.sampled_from("ABCDE"), min_size=d, max_size=d, unique=True)))
    kw: dict = {"state_names": names}
    if draw(st.booleans()):
        kind = draw(st.sampled_from(["previous", "linear"]))
        S = draw(st.integers(1, 3))
        knots = [torch.cumsum(0.3 + torch.rand(S, generator=g, dtype=DT), 0) for _ in range(K)]
        kw["controls"] = Controls(knots, [torch.rand(S, 1, generator=g, dtype=DT) for _ in range(K)], kind=kind,
                                  names=["u"])  # fmt: skip
    if draw(st.booleans()):
        weights = {"r": {(names or [f"y{j}" for j in range(d)])[0]: 2.0}}
        kw["readout"] = tms.Readout.from_weights(weights, names or [f"y{j}" for j in range(d)])
        kw["readings"] = [kw["readout"](y) for y in states]
    if draw(st.booleans()):
        kw["initial_states"] = torch.randn(K, d, generator=g, dtype=DT)
    if not ragged:
        times, states = times[0], torch.stack(states)
        if "readings" in kw:
            kw["readings"] = torch.stack(kw["readings"])
    data = tms.Trajectories(times, states, **kw)
    return data.to(torch.float32) if draw(st.booleans()) else data


def _load_back(data: tms.Trajectories, path):
    options = {}
    if path.suffix != ".npz":
        if data.controls is not None:
            options["control_columns"] = list(data.controls.names)
        if data.readout is not None:
            options["readout"] = data.readout
            options["state_columns"] = list(data.state_names)
    return tms.Trajectories.load(path, **options)


@FAST
@given(trajectories_strategy(), st.sampled_from(["npz", "csv", "tsv", "txt"]))
def test_saving_and_loading_keeps_every_field_or_refuses(tmp_path_factory, data, suffix):
    """Every format gives back every field as it was (a text table as float64), or refuses the field it cannot
    hold, naming it; never a Trajectories with a field dropped or read otherwise."""
    path = tmp_path_factory.mktemp("trip") / f"data.{suffix}"
    try:
        data.save(path)
    except tms.TorchMisspecError as exc:
        refused(exc)
        assert suffix != "npz", f"an archive refused {data}: {exc}"
        assert data.initial_states is not None or data.controls.kind == "linear", str(exc)
        return
    back = _load_back(data, path)
    same_trajectories(data if suffix == "npz" else data.to(torch.float64), back, samples=suffix == "npz")
    assert back.dtype == (data.dtype if suffix == "npz" else torch.float64)


@pytest.mark.slow
@LONG
@given(trajectories_strategy(), st.sampled_from(["npz", "csv", "tsv", "txt"]))
def test_saving_and_loading_keeps_every_field_or_refuses_long(tmp_path_factory, data, suffix):
    test_saving_and_loading_keeps_every_field_or_refuses.hypothesis.inner_test(tmp_path_factory, data, suffix)


# -------------------------------------------------------------------------------- 3. one batch, or two calls
@FAST
@given(st.integers(1, 3))
def test_splitting_a_batch_of_experiments_gives_the_same_results(cut):
    """simulate, predict, the correction samples and the posterior mean path of experiments [:cut] and [cut:] in two
    calls equal the batch's (each experiment with its own controls, whatever it is batched with)."""
    parts = [slice(0, cut), slice(cut, None)]
    sims = [tms.simulate(CHEMO, CY0[p], CTIMES, controls=CCONTROLS[p]).states for p in parts]
    same(torch.cat(sims), CTRAJ.states, rtol=1e-7, atol=1e-10, what="simulate")
    whole = CMODEL.predict(CY0, CTIMES, controls=CCONTROLS)
    preds = [CMODEL.predict(CY0[p], CTIMES, controls=CCONTROLS[p]) for p in parts]
    same(torch.cat(preds), whole, rtol=1e-6, atol=1e-9, what="predict")
    samples = [tms.correction_samples(CTRAJ[p], CHEMO, derivative="central") for p in parts]
    base = tms.correction_samples(CTRAJ, CHEMO, derivative="central")
    same(torch.cat([s.targets for s in samples]), base.targets, what="samples")
    same(torch.cat([s.inputs for s in samples]), base.inputs, what="sample inputs")


@FAST
@given(st.permutations([0, 1, 2, 3]))
def test_the_experiments_in_another_order_are_predicted_in_that_order(order):
    got = CMODEL.predict(CY0[order], CTIMES, controls=CCONTROLS[order])
    same(got, CMODEL.predict(CY0, CTIMES, controls=CCONTROLS)[order], rtol=1e-6, atol=1e-9)


# ------------------------------------------------------------------------------------------ 4. dtypes and units
@FAST
@given(st.sampled_from([torch.float32, torch.float64]))
def test_float32_and_float64_follow_the_tensors(dtype):
    """Values in a dtype give results in it (simulate, controls, readout, trajectories' fields); a model predicts
    in its own dtype, and a float32 model agrees with the float64 one to float32's precision."""
    sim = tms.simulate(CHEMO, CY0.to(dtype), CTIMES.to(dtype), controls=CCONTROLS)
    assert sim.dtype == dtype and sim.controls.values.dtype == dtype
    same(sim.states, CTRAJ.states, rtol=1e-4 if dtype == torch.float32 else 1e-9, atol=1e-6)
    assert Controls(CKNOTS.to(dtype), CVALUES.to(dtype)).at(CTIMES.to(dtype).expand(4, -1)).dtype == dtype
    readout = tms.Readout.parse(["total = X + S"], ["X", "S"])
    moved = CTRAJ.with_readout(readout).with_initial_states(CY0).to(dtype)
    fields = [
        moved.states,
        moved.times,
        moved.readings,
        moved.initial_states,
        moved.controls.values,
        moved.readout.matrix,
    ]
    assert all(t.dtype == dtype for t in fields)
    model = tms.CorrectedODE(LIN, tms.CorrectionGP(**HYPER, dtype=dtype).fit(SAMPLES.inputs, SAMPLES.targets))
    pred = model.predict(Y0.to(torch.float64 if dtype == torch.float32 else torch.float32), TIMES)
    assert pred.dtype == dtype
    same(pred, tms.CorrectedODE(LIN, GP).predict(Y0, TIMES), rtol=1e-4, atol=1e-6, what="float32 model")


@FAST
@given(st.sampled_from([1e-3, 1e-2, 1e2, 1e3]))
def test_a_change_of_units_scales_the_model_and_its_prediction(c):
    """States in other units (y -> c y) with the GP's hyperparameters in those units: the correction and the
    corrected model's paths scale by c (G is linear), to the solver's relative tolerance."""
    A = torch.tensor(((0.02, 0.10), (-0.10, -0.06)), dtype=DT)
    system = tms.MisspecifiedSystem(tms.systems.LinearField(A), 2, name="linear")
    gp = tms.CorrectionGP(lengthscale=c, outputscale=4e-5 * c**2, noise_variance=1e-6 * c**2)
    gp.fit(c * SAMPLES.inputs, c * SAMPLES.targets)
    same(gp.predict_mean(c * Y0), c * GP.predict_mean(Y0), rtol=1e-9, atol=0, what="the correction in new units")
    base = tms.CorrectedODE(system, GP).predict(Y0, TIMES)
    same(tms.CorrectedODE(system, gp).predict(c * Y0, TIMES), c * base, rtol=1e-6, atol=0, what="the path")


# ------------------------------------------------------------------------------- 5. subsets, dtypes and refusals
index_strategy = st.one_of(
    st.integers(-6, 6),
    st.lists(st.integers(-5, 5), max_size=4),
    st.lists(st.booleans(), min_size=1, max_size=5),
    st.builds(slice, st.none() | st.integers(-4, 4), st.none() | st.integers(-4, 4), st.none() | st.integers(-2, 2)),
    st.sampled_from([None, "a", 1.5, [0.5], True, (0, 1), {0: 1}, ..., 10**30, np.array([0, 2]), torch.tensor([1]),
                     torch.tensor([True, False, True, False]), torch.tensor([0.5]), torch.tensor([[0, 1]]), CCONTROLS,
                     CTRAJ, (torch.tensor([[0.1, 0.2]]), CCONTROLS)]),
)  # fmt: skip


def _manual_selection(index, K):
    """What ``index`` selects among K experiments by Python's rules (None when it is not a selection of them)."""
    positions = list(range(K))
    if isinstance(index, slice):
        try:
            return positions[index]
        except ValueError:
            return None
    if isinstance(index, torch.Tensor):
        if index.dim() != 1 or index.is_floating_point():
            return None
        index = index.tolist()
    if isinstance(index, (np.ndarray, tuple)):  # a tuple of positions is a list of them (the data are 1-D)
        index = list(index.tolist() if isinstance(index, np.ndarray) else index)
    if isinstance(index, int) and not isinstance(index, bool):
        return [positions[index]] if -K <= index < K else None
    if isinstance(index, list) and index and all(isinstance(i, bool) for i in index):
        return [k for k, keep in zip(positions, index, strict=True) if keep] if len(index) == K else None
    if isinstance(index, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in index):
        return [positions[i] for i in index] if all(-K <= i < K for i in index) else None
    return None


@FAST
@given(index_strategy)
def test_a_subset_of_experiments_is_the_one_asked_for_or_refused(index):
    """trajectories[index] and controls[index] hold the experiments Python's indexing rules pick, in that order,
    or refuse with a package error (a float, a string, an object, a mask of another length, none at all); an
    object with __getitem__ as an index crashed the interpreter before."""
    K = CTRAJ.num_experiments
    want = _manual_selection(index, K)
    for whole in (CTRAJ, CCONTROLS):
        try:
            got = whole[index]
        except tms.TorchMisspecError as exc:
            refused(exc)
            assert not want, f"{index!r} refused, which selects {want}"
            continue
        assert want, f"{index!r} accepted"
        if isinstance(whole, tms.Trajectories):
            same(got.states, CTRAJ.states[want], rtol=0)
            same(got.controls.values, CCONTROLS.values[want], rtol=0)
        else:
            same(got.values, CCONTROLS.values[want], rtol=0)


@FAST
@given(st.sampled_from([torch.float32, torch.float64, "cpu", torch.int64, torch.complex128, torch.bool, "bogus", 3,
                        None, "float32"]))  # fmt: skip
def test_to_gives_the_dtype_asked_for_or_refuses(arg):
    """.to() of trajectories, controls and readouts: every field in the real floating dtype asked for, or a
    refusal (an integer dtype was silently kept as float64)."""
    readout = tms.Readout.parse(["total = X + S"], ["X", "S"])
    for obj in (CTRAJ.with_readout(readout), CCONTROLS, readout):
        try:
            out = obj.to(arg)
        except tms.TorchMisspecError as exc:
            refused(exc)
            assert arg not in (torch.float32, torch.float64, "cpu", None)
            continue
        want = arg if isinstance(arg, torch.dtype) else torch.float64
        dtype = out.dtype if isinstance(out, tms.Trajectories) else out.values.dtype if isinstance(out, Controls) else (
            out.matrix.dtype
        )  # fmt: skip
        assert dtype == want, (arg, dtype)


# ------------------------------------------------------------------------------- 6. partial and ragged data
@FAST
@given(st.integers(0, 3), st.integers(1, 8))
def test_masking_a_whole_row_is_deleting_it(k, t):
    """A time at which nothing was observed (every state NaN) is the same data as that row deleted: the same
    trajectories and the same correction samples."""
    states = CTRAJ.states.clone()
    states[k, t] = float("nan")
    masked = tms.Trajectories(CTIMES, states, state_names=["X", "S"], controls=CCONTROLS)
    keep = [i for i in range(len(CTIMES)) if i != t]
    rows = [
        (CTIMES[keep] if j == k else CTIMES, CTRAJ.states[j, keep] if j == k else CTRAJ.states[j]) for j in range(4)
    ]
    deleted = tms.Trajectories([r[0] for r in rows], [r[1] for r in rows], state_names=["X", "S"], controls=CCONTROLS)
    same_trajectories(masked, deleted)
    a = tms.correction_samples(masked, CHEMO, derivative="central")
    b = tms.correction_samples(deleted, CHEMO, derivative="central")
    same(a.targets, b.targets, what="samples")


@FAST
@given(st.lists(st.integers(3, 9), min_size=1, max_size=4))
def test_ragged_data_is_each_experiment_on_its_own(lengths):
    """Experiments of different lengths, simulated and sampled in one call, equal each experiment alone; lists of
    equal lengths are the stacked form."""
    K = len(lengths)
    grids = [CTIMES[:n] for n in lengths]
    sim = tms.simulate(CHEMO, CY0[:K], grids, controls=CCONTROLS[:K])
    for k, (t, y) in enumerate(sim.experiments()):
        alone = tms.simulate(CHEMO, CY0[k : k + 1], grids[k], controls=CCONTROLS[[k]]).states[0]
        # the stacked solve shares its adaptive steps with the other experiments: the two agree to what an
        # rtol=1e-10 solve through piecewise-constant inputs achieves (both measured ~1e-8 from an rtol=1e-13 solve)
        same(y, alone, rtol=1e-7, atol=1e-9, what=f"experiment {k}")
        same(t, grids[k], rtol=0)
    if len(set(lengths)) == 1:
        assert not sim.is_ragged
    samples = tms.correction_samples(sim, CHEMO, derivative="central")
    each = [tms.correction_samples(sim[k], CHEMO, derivative="central").targets for k in range(K)]
    same(samples.targets, torch.cat(each), rtol=1e-10, atol=1e-13, what="samples")


# ---------------------------------------------------------------------------------------- 7. designs and executors
CANDS = torch.tensor([[0.3, 0.6], [0.4, 0.5], [0.2, 0.8], [0.5, 0.3], [0.6, 0.6], [0.1, 0.2]], dtype=DT)
CAND_CONTROLS = Controls(CKNOTS, torch.rand(6, 3, 1, generator=torch.Generator().manual_seed(2), dtype=DT) * 0.3,
                         names=["D"])  # fmt: skip
PRIOR = tms.CorrectionGP(lengthscale=0.5, outputscale=1e-2, noise_variance=1e-4)


def _design(candidates=CANDS, controls=CAND_CONTROLS, executor=None, budget=3):
    return tms.design.greedy(candidates, budget, system=CHEMO, times=CTIMES, gp=PRIOR, controls=controls,
                             executor=executor)  # fmt: skip


DESIGN = _design()


@FAST
@given(st.permutations(list(range(6))))
def test_candidates_permuted_with_their_controls_give_the_same_design(order):
    """The candidates in another order, each with its own input profile: the same experiments chosen (their
    points and profiles) and the same information gain."""
    got = _design(CANDS[order], CAND_CONTROLS[order])
    picked = sorted(order[i] for i in got.indices.tolist())
    assert picked == sorted(DESIGN.indices.tolist())
    assert got.information_gain == pytest.approx(DESIGN.information_gain, rel=1e-9)


def test_an_executor_gives_the_design_and_the_calibration_of_none():
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        got = _design(executor=pool)
        assert got.indices.tolist() == DESIGN.indices.tolist()
        assert got.information_gain == pytest.approx(DESIGN.information_gain, rel=1e-12)
        results = tms.parallel.map_tasks(math.sqrt, [4.0, 9.0, 16.0], pool)
    assert results == [2.0, 3.0, 4.0]


@FAST
@given(st.integers(1, 9), st.integers(1, 3))
def test_sampling_times_spend_each_budget_on_candidate_times(per, K):
    """Each experiment gets exactly ``per_experiment`` of the candidate times, increasing (all of them when the
    budget is every time), the same again on a second call. (Reordering the experiments may change the choice:
    every single time has the same prior gain, and greedy breaks that tie by position.)"""
    chosen = tms.design.sampling_times(CY0[:K], CTIMES, per, system=CHEMO, gp=PRIOR, controls=CCONTROLS[:K])
    again = tms.design.sampling_times(CY0[:K], CTIMES, per, system=CHEMO, gp=PRIOR, controls=CCONTROLS[:K])
    assert len(chosen.times) == K
    for t, u in zip(chosen.times, again.times, strict=True):
        assert len(t) == per and bool((t.diff() > 0).all()) and set(t.tolist()) <= set(CTIMES.tolist())
        same(t, u, rtol=0)


# -------------------------------------------------------------------------------------- 8. saved models and draws
@FAST
@given(st.sampled_from(["rbf", "matern52", "polynomial", "per_output", "float32", "chemo", "input_scale"]))
def test_a_saved_model_predicts_as_the_original(tmp_path_factory, kind):
    """Every kind of model, saved and loaded: the same means and variances, dtype and input names."""
    X, Y = SAMPLES.inputs, SAMPLES.targets
    models = {
        "rbf": lambda: GP,
        "matern52": lambda: tms.CorrectionGP(kernel="matern52", max_iter=5).fit(X, Y),
        "polynomial": lambda: tms.CorrectionGP(kernel="polynomial", max_iter=5).fit(X, Y),
        "per_output": lambda: tms.CorrectionGP(per_output=True, max_iter=5).fit(X, Y),
        "float32": lambda: tms.CorrectionGP(dtype=torch.float32, noise_variance=1e-4, max_iter=5).fit(X, Y),
        "chemo": lambda: CGP,
        "input_scale": lambda: tms.CorrectionGP(kernel=tms.gp.RBF(input_scale=[1.0, 10.0]), max_iter=5).fit(X, Y),
    }
    model = models[kind]()
    back = tms.CorrectionGP.load(model.save(tmp_path_factory.mktemp("gp") / "gp.pt"))
    x = torch.rand(7, model.input_dim, generator=torch.Generator().manual_seed(0), dtype=model.dtype)
    a, b = model.predict(x), back.predict(x)
    # relative to their size: with a noise variance near 1e-13 the refactorized solve differs from the original's in
    # about the 12th digit when torch runs 2 threads (1.4e-14 on means of 0.0075); with 1 thread it is bit-identical
    same(b.mean, a.mean, rtol=1e-9, atol=1e-9 * float(a.mean.abs().max()), what=f"{kind} mean")
    same(b.variance, a.variance, rtol=1e-10, atol=1e-10 * float(a.variance.abs().max()), what=f"{kind} variance")
    assert back.dtype == model.dtype and getattr(back, "input_names_", None) == getattr(model, "input_names_", None)


@FAST
@given(st.integers(0, 2**16), st.integers(1, 3))
def test_posterior_draws_are_reproducible_and_read_by_name(seed, K):
    """The same generator gives the same draws; a readout over the states' names in another order reads each
    draw by name; the band's interval holds its median."""

    def draws():
        return CMODEL.posterior(CY0[:K], CTIMES, controls=CCONTROLS[:K], num_samples=19, scale=1.0,
                                generator=torch.Generator().manual_seed(seed))  # fmt: skip

    a, b = draws(), draws()
    same(a.samples, b.samples, rtol=0)
    read = a.read(tms.Readout.parse(["z = 2*S - X"], ["S", "X"]))
    same(read.samples[..., 0], 2 * a.samples[..., 1] - a.samples[..., 0], rtol=1e-12, atol=1e-14)
    lo, hi = a.interval(0.9)
    median = a.quantile(0.5)
    assert bool((lo <= median).all() and (median <= hi).all())


# ---------------------------------------------------------------------------------- 9. uncertain parameters
@FAST
@given(st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2))
def test_a_system_at_theta_is_g_with_theta(theta, y1, y2):
    """system.at(theta) calls G with that theta (and only fixes it: the uncertain parameters are gone)."""
    system = oscillator()
    y = torch.tensor([[y1, y2]], dtype=DT)
    fixed = system.at([theta])
    same(fixed.known_rhs(y), torch.tensor([[y2, -y1 - theta * y2]], dtype=DT), rtol=1e-15, atol=1e-15)
    assert fixed.parameters is None and system.parameters is not None
    with pytest.raises(tms.ShapeError) as info:
        system.at([theta, theta])
    refused(info.value)


# ------------------------------------------------------------- 10. what a sweep of the 0.2 surface found (fixed)
def test_an_object_with_getitem_as_an_index_is_refused_not_a_crash():
    """A tensor indexed with a tuple holding a Controls (what Campaign.ask returns, taken for indices) recursed
    through its __getitem__ inside torch and killed the interpreter (a segmentation fault); so did a Trajectories."""
    points, profiles = CANDS[:2], CAND_CONTROLS[:2]
    with pytest.raises(tms.InputError, match=r"__getitem__: expected tensors \(or indices\), got a Controls"):
        CANDS[(points, profiles)]
    with pytest.raises(tms.InputError, match=r"__getitem__: expected tensors \(or indices\), got a Trajectories"):
        CANDS[(points, CTRAJ[:2])]
    with pytest.raises(tms.InputError, match=r"stack: expected tensors"):
        torch.stack([CTRAJ])
    for whole in (CCONTROLS, CTRAJ):
        with pytest.raises(tms.InputError, match=r"index: expected positions among the 4 experiments .*got"):
            whole[(points, profiles)]
        with pytest.raises(tms.InputError, match=r"index: expected an integer, a slice, .*got Controls"):
            whole[profiles]
        assert [len(one) for one in whole] == [1] * 4  # iterating stops at the end (no IndexError needed)


def test_to_an_integer_dtype_is_refused_not_kept_as_float64():
    with pytest.raises(tms.InputError, match=r"Trajectories.to: expected a real floating dtype .*got torch.int64"):
        CTRAJ.to(torch.int64)
    with pytest.raises(tms.InputError, match=r"Controls.to: expected a device .*got 'bogus'"):
        CCONTROLS.to("bogus")


def test_simulate_names_the_states_as_the_system_does():
    """The simulation of a system with named states carries the names (it was named y0, y1: a readout or a model
    over the names then read the columns by position, and a saved table had other columns than the system's)."""
    assert CTRAJ.state_names == ("X", "S")
    ragged = tms.simulate(CHEMO, CY0[:2], [CTIMES, CTIMES[:4]], controls=CCONTROLS[:2])
    assert ragged.state_names == ("X", "S")


@pytest.mark.parametrize("tolerance", [{"rtol": 1.0}, {"atol": 1e300}, {"rtol": 2.5}])
def test_a_tolerance_of_one_or_more_is_refused(tolerance):
    """rtol=1e300 integrated in one step to states of 1e56 (returned as the simulation); a tolerance as large as the
    states accepts any path."""
    with pytest.raises(tms.InputError, match=r"tol: expected a tolerance below 1 .*got"):
        tms.simulate(CHEMO, CY0, CTIMES, controls=CCONTROLS, **tolerance)
    with pytest.raises(tms.InputError, match=r"tol: expected a tolerance below 1"):
        CMODEL.predict(CY0, CTIMES, controls=CCONTROLS, solver=tms.Solver(**tolerance))


def test_the_systems_methods_take_arrays_and_check_the_states_before_g_sees_them():
    """known_rhs etc. of a list or array raised AttributeError; states of the wrong width were passed to the user's
    G, and its failure was reported as an error in the user's code."""
    u = [[0.2], [0.2], [0.2], [0.2]]
    same(CHEMO.known_rhs(CY0.tolist(), 0.0, u), CHEMO.known_rhs(CY0, 0.0, torch.tensor(u, dtype=DT)), rtol=0)
    same(CHEMO.select_inputs(CY0.numpy(), u), CHEMO.select_inputs(CY0, torch.tensor(u, dtype=DT)), rtol=0)
    with pytest.raises(tms.ShapeError, match=r"y: expected a last dimension of size state_dim=2 .*got shape \(4, 1\)"):
        CHEMO.known_rhs(CY0[:, :1], 0.0, u)
    with pytest.raises(tms.ShapeError, match=r"x: expected a last dimension of size 2 \(the correction inputs"):
        CHEMO.true_correction(CY0[:, :1])
    with pytest.raises(tms.ShapeError, match=r"t: expected one value or values of shape \(4,\), got shape \(3,\)"):
        CHEMO.known_rhs(CY0, torch.zeros(3, dtype=DT), u)
    with pytest.raises(tms.InputError, match=r"t: expected an array of real numbers, got str"):
        CHEMO.known_rhs(CY0, "0", u)
    with pytest.raises(tms.InputError, match=r"y: expected an array of real numbers"):
        tms.CorrectedODE(LIN, GP).correction("abc")


def test_the_builtin_fields_check_their_arguments_and_states():
    with pytest.raises(tms.ShapeError, match=r"y: expected a last dimension of size 3 .*got shape \(3, 2\)"):
        tms.systems.LinearField(torch.eye(3, dtype=DT))(Y0)
    with pytest.raises(tms.ShapeError, match=r"matrix: expected a square \(d, d\) matrix"):
        tms.systems.LinearField(torch.ones(2, 3))
    with pytest.raises(tms.InputError, match=r"coef: expected a finite number, got nan"):
        tms.systems.QuadraticField(float("nan"))
    with pytest.raises(tms.ShapeError, match=r"positions: expected \(2, 2\) positions, one \(x1, x2\) per mass"):
        tms.systems.PointMassGravity([1.0, 2.0], [[0.0, 0.0]])
    with pytest.raises(tms.ShapeError, match=r"x: expected a last dimension of size 2 \(positions"):
        tms.systems.PointMassGravity([1.0], [[0.0, 0.0]])(torch.ones(3, 4, dtype=DT))


def test_readout_names_and_definitions_are_checked():
    with pytest.raises(tms.InputError, match=r"state_names: expected a list of 2 names"):
        tms.Readout([[1.0, 2.0]], ["z"], state_names=3)
    with pytest.raises(tms.InputError, match=r"definitions: expected a list of strings .*got None"):
        tms.Readout.parse(None, ["a", "b"])
    with pytest.raises(tms.InputError, match=r"state_names: expected a list of the states' names, got None"):
        tms.Readout.from_weights({"z": {"a": 1.0}}, None)
    with pytest.raises(tms.InputError, match=r"weights\['z'\]\['a'\]: expected a finite number, got an integer of"):
        tms.Readout.from_weights({"z": {"a": 10**400}}, ["a", "b"])
    with pytest.raises(tms.ShapeError, match=r"state_names: expected 2 non-empty strings"):
        tms.Readout([[1.0, 2.0]], ["z"]).describe(["p"])
    with pytest.raises(tms.InputError, match=r"readout: expected a torchmisspec.data.Readout or None, got str"):
        CTRAJ.with_readout("total = X + S")


def test_a_control_function_is_called_as_the_users_code_and_must_be_finite():
    failing = Controls.from_function(lambda t: (1 / 0) * t, 2, 1)
    with pytest.raises(tms.InputError, match=r"u\(t\) raised ZeroDivisionError"):
        failing.at(CTIMES.expand(2, -1))
    with pytest.raises(tms.InputError, match=r"controls: expected u\(t\) finite at every time .*got NaN or inf"):
        Controls.from_function(lambda t: (t * math.nan).unsqueeze(-1), 2, 1).at(CTIMES.expand(2, -1))
    with pytest.raises(tms.InputError, match=r"t: expected an array of real numbers, got str"):
        CCONTROLS.at("t")
    with pytest.raises(tms.ShapeError, match=r"knots: expected 1 knot arrays \(one per experiment\), got 2"):
        Controls([CKNOTS, CKNOTS], [CVALUES[0]])


def test_files_that_cannot_be_written_and_column_lists_that_are_not_lists_are_refused(tmp_path):
    for write in (lambda p: CTRAJ.save(p), lambda p: GP.save(p)):
        with pytest.raises(tms.InputError, match=r"path: expected a file in an existing folder"):
            write(tmp_path / "no" / "file.csv")
        with pytest.raises(tms.InputError, match=r"path: expected a file name, got the folder"):
            write(tmp_path)
    CTRAJ.save(tmp_path / "c.csv")
    with pytest.raises(tms.InputError, match=r"state_columns: expected a list of column names, got 3"):
        tms.Trajectories.load(tmp_path / "c.csv", state_columns=3)
    with pytest.raises(tms.InputError, match=r"control_columns: expected a list of column names, got 3"):
        tms.Trajectories.load(tmp_path / "c.csv", control_columns=3)


def test_a_failed_write_is_a_package_error(tmp_path, monkeypatch):
    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full_disk)
    with pytest.raises(tms.InputError, match=r"path: expected a file that can be written, got .*No space left"):
        CTRAJ.save(tmp_path / "c.npz")


def test_gp_settings_and_posterior_inputs_are_checked():
    with pytest.raises(tms.InputError, match=r"device: expected a device that holds values, 'cpu' or 'cuda', got"):
        tms.CorrectionGP(device="meta")
    with pytest.raises(tms.InputError, match=r"dtype: expected a floating torch.dtype .*got torch.float16"):
        tms.CorrectionGP(dtype=torch.float16)
    posterior = GP.posterior()
    with pytest.raises(tms.ShapeError, match=r"targets: expected \(21, 2\) targets .*got shape \(2, 2\)"):
        posterior.with_targets(SAMPLES.targets[:2])
    with pytest.raises(tms.InputError, match=r"x: expected an array of real numbers, got str"):
        posterior.sd_ratio("a")


def test_metrics_design_and_cross_validation_arguments_are_checked():
    with pytest.raises(tms.InputError, match=r"dim: expected an integer <= 0, got 1"):
        tms.metrics.mean_and_standard_error([1.0, 2.0], dim=1)
    with pytest.raises(tms.InputError, match=r"dtype: expected torch.float64 or torch.float32, got 'a'"):
        tms.metrics.box_grid(((0, 1),), 3, dtype="a")
    with pytest.raises(tms.ShapeError, match=r"field: expected values \(M, m\) at M = 9 points, got str"):
        tms.integrated_norm(lambda x: "a", ((0, 1),), resolution=9)
    with pytest.raises(tms.InputError, match=r"candidates: expected a non-empty list of CorrectionGP templates, got 3"):
        tms.cross_validate(CHEMO, CTRAJ, CSAMPLES, 3)
    with pytest.raises(tms.InputError, match=r"epsilon: expected a positive finite number"):
        tms.design.greedy(
            CANDS,
            2,
            system=CHEMO,
            times=CTIMES,
            gp=PRIOR,
            controls=CAND_CONTROLS,
            engine=tms.design.Engine(epsilon=torch.tensor([1, 2])),
        )


def test_map_tasks_and_the_parameters_helpers_check_their_arguments():
    with pytest.raises(tms.InputError, match=r"fn: expected a callable fn\(task\), got None"):
        tms.parallel.map_tasks(None, [1])
    with pytest.raises(tms.InputError, match=r"tasks: expected a list \(an iterable\) of tasks, got 3"):
        tms.parallel.map_tasks(math.sqrt, 3)
    with pytest.raises(tms.InputError, match=r"each: expected a callable each\(result\) .*got a callable taking \(\)"):
        tms.parallel.map_tasks(math.sqrt, [1.0], each=lambda: None)
    with pytest.raises(tms.InputError, match=r"rhs: expected a callable rhs\(theta\)"):
        tms.parameters.jacobian("a", torch.tensor([1.0]), torch.tensor([0.1]))
    posterior = tms.parameters.ParameterPosterior.prior(oscillator().parameters, 5, 1, SAMPLES.inputs)
    assert posterior.sample(3, torch.Generator().manual_seed(0)).shape == (3, 1)
    with pytest.raises(tms.InputError, match=r"num_samples: expected an integer >= 0, got 'a'"):
        posterior.sample("a")
    with pytest.raises(tms.InputError, match=r"generator: expected a torch.Generator or None, got int"):
        posterior.sample(2, 3)


def test_simulate_and_the_samples_check_their_objects():
    with pytest.raises(tms.InputError, match=r"system: expected a MisspecifiedSystem, got str"):
        tms.simulate("paper_linear", Y0, TIMES)
    with pytest.raises(tms.InputError, match=r"known_only: expected True or False, got 1"):
        tms.simulate(LIN, Y0, TIMES, known_only=1)
    with pytest.raises(tms.InputError, match=r"trajectories: expected a torchmisspec.Trajectories, got NoneType"):
        tms.data.simulate_known_each(LIN, None)
    with pytest.raises(tms.InputError, match=r"rows: expected positions among the 36 samples"):
        CSAMPLES.subset(torch.tensor([10**6]))
    with pytest.raises(tms.InputError, match=r"samples: expected samples of a system with uncertain parameters"):
        CSAMPLES.shifted(torch.zeros(1), [0])
    with pytest.raises(tms.InputError, match=r"noise_std: expected a standard deviation whose square is finite"):
        tms.correction_samples(CTRAJ, CHEMO, derivative="auto", noise_std=1e300)  # OverflowError before


def test_a_model_of_other_inputs_is_refused_where_it_is_used():
    """A model fitted on the inputs (X, D), used with a system whose correction reads (S, D) or (D, X): the same
    number of inputs, so it ran, reading S as X. Refused now, naming both; names that are only positions (y0, u0)
    do not count."""
    gp = tms.CorrectionGP(lengthscale=0.5, outputscale=1e-2, noise_variance=1e-6).fit(CSAMPLES.inputs, CSAMPLES.targets)
    gp.input_names_ = ("X", "D")  # as fit_correction records them
    assert tms.CorrectedODE(CHEMO, gp).predict(CY0, CTIMES, controls=CCONTROLS).shape == (4, 9, 2)
    unnamed_control = chemostat(control_names=None, correction_inputs=[0, 2])
    tms.CorrectedODE(unnamed_control, gp)  # u0 is a position, not a name
    for inputs, order in ((["S", "D"], "other names"), (["D", "X"], "the same names in another order")):
        other = chemostat(correction_inputs=inputs)
        with pytest.raises(tms.InputError, match=rf"gp: expected a model of the correction inputs .*got one fitted on "
                                                 rf"\['X', 'D'\] \({order}\)"):  # fmt: skip
            tms.CorrectedODE(other, gp)
        with pytest.raises(tms.InputError, match=r"gp: expected a model of the correction inputs"):
            tms.design.greedy(CANDS, 2, system=other, times=CTIMES, gp=gp, controls=CAND_CONTROLS)
        with pytest.raises(tms.InputError, match=r"gp: expected a model of the correction inputs"):
            tms.correction_error(gp, other, domain=((0, 1), (0, 1)), resolution=3)


# ------------------------------------------------------------------------------------- the long profile (-m slow)
@pytest.mark.slow
@LONG
@given(index_strategy, st.sampled_from([torch.float32, torch.float64, "cpu", torch.int64, "bogus", None]))
def test_subsets_and_dtypes_long(index, arg):
    test_a_subset_of_experiments_is_the_one_asked_for_or_refused.hypothesis.inner_test(index)
    test_to_gives_the_dtype_asked_for_or_refuses.hypothesis.inner_test(arg)


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.permutations([0, 1, 2]), st.lists(st.floats(-3, 3).filter(lambda w: abs(w) > 1e-3), min_size=3, max_size=3),
       st.integers(0, 3), st.integers(1, 8), st.lists(st.integers(3, 9), min_size=1, max_size=4))  # fmt: skip
def test_names_masks_and_ragged_data_long(order, weights, k, t, lengths):
    test_states_permuted_with_their_names_give_the_same_samples_or_a_refusal.hypothesis.inner_test(order)
    test_a_readout_over_names_in_any_order_reads_the_same_numbers.hypothesis.inner_test(order, weights)
    test_masking_a_whole_row_is_deleting_it.hypothesis.inner_test(k, t)
    test_ragged_data_is_each_experiment_on_its_own.hypothesis.inner_test(lengths)


def test_a_g_of_the_wrong_shape_is_refused_by_the_fit_in_any_units():
    """G returning (..., 1) for two states: refused on data of order 1, but on data of order 1e-3 (fitted in the
    data's units, G_z(z) = G(s z) / s) the division by the two scales broadcast it to (..., 2) before the shape
    check, and the fit returned a model."""
    narrow = tms.MisspecifiedSystem(lambda y: -y[..., :1], 2, correction=lambda y: 0.1 * y**2, name="narrow")
    data = tms.simulate(LIN, Y0, TIMES)
    for c in (1.0, 1e-3):
        small = tms.Trajectories(TIMES, c * data.states)
        with pytest.raises(tms.ShapeError, match=r"system 'narrow': G returned shape \(\d+, 1\)"):
            tms.fit_correction(small, narrow, derivative="central", folds=2, refine=False, progress=False)
