"""Public measurements of dynamics, each with the mechanistic model a scientist would write for it (offline).

``load(name)`` gives a :class:`Dataset`: the measurements as :class:`~torchmisspec.Trajectories` (read with
:meth:`Trajectories.load <torchmisspec.Trajectories.load>` from a small CSV shipped with the package), the model as a
:class:`~torchmisspec.MisspecifiedSystem` (its state names, its uncertain parameters with Gaussian priors, no true
correction: nobody knows it), the citation and a one-line description. :func:`names` lists them. What is not
measured is NaN in the trajectories (a component measured fewer than three times in an experiment, e.g. a dose
known only at the start, is *not measured* there, see :attr:`Trajectories.measured
<torchmisspec.Trajectories.measured>`).

The data sets (sources, units and licences also in ``torchmisspec/datasets/data/README.md``):

* ``orange``: R ``datasets::Orange`` (Draper & Smith, *Applied Regression Analysis*, Wiley, 1981; exercise 24.N in the
  R documentation's 1998 edition): trunk circumference (mm) of 5 orange trees at 7 ages (days). Model: logistic growth
  dC/dt = r C (1 - C/K), r and K uncertain.
* ``loblolly``: R ``datasets::Loblolly`` (Kung 1986, "Fitting logistic growth curve with predetermined
  carrying capacity", ASA Proceedings of the Statistical Computing Section, 340-343): height (ft) of 14 loblolly
  pines (seed sources) at 6 ages (years). Model: monomolecular growth dh/dt = k (A - h), k and A uncertain.
* ``chickweight``: R ``datasets::ChickWeight`` (Crowder & Hand 1990, *Analysis of Repeated Measures*, Chapman &
  Hall, example 5.3): body weight (g) of 50 chicks on 4 diets, every second day from day 0 to 21 (chicks that died
  early have fewer measurements; the diet is in the CSV, the model ignores it). Model: logistic growth
  dW/dt = r W (1 - W/K), r and K uncertain.
* ``theoph``: R ``datasets::Theoph`` (Boeckmann, Sheiner & Beal 1994, *NONMEM Users Guide Part V*): theophylline
  concentration (mg/L) in 12 subjects after an oral dose (mg/kg), over 25 hours. Model: one compartment with
  first-order absorption, d gut/dt = -ka gut, d conc/dt = ka gut / V - ke conc, ka, ke, V uncertain; the gut amount
  is not measured (its column holds the dose at time 0, the gut's initial state, and nothing after).
* ``lynx``: R ``datasets::lynx`` (Brockwell & Davis 1991, *Time Series and Forecasting Methods*, Springer, series
  G; Campbell & Walker 1977, JRSS A 140:411-431): annual Canadian lynx trappings 1821-1934 (counts), one
  trajectory. Model: Lotka-Volterra with the hares unmeasured, d hare/dt = a hare - b hare lynx,
  d lynx/dt = d hare lynx - c lynx, a, b, c uncertain; d = 1e-3 fixed (the hares' unit, which lynx counts alone
  cannot set).
* ``hare_lynx``: Hudson's Bay Company hare and lynx pelts 1900-1920 (thousands), one trajectory (Hewitt 1921,
  *The Conservation of the Wild Life of Canada*; Odum 1953, *Fundamentals of Ecology*; as tabulated by Howard 2009,
  taken from stan-dev/example-models, ``knitr/lotka-volterra/hudson-bay-lynx-hare.csv``). Model: Lotka-Volterra
  with its four rates uncertain.
* ``influenza``: influenza in a boarding school (Anonymous, "Influenza in a boarding school", BMJ 1978, 4 March,
  1:587): 763 boys, one index case, the number confined to bed on days 1-14 (R ``outbreaks::
  influenza_england_1978_school``, taken from epirecipes/Outbreaks.jl, ``data/influenza_england_1978_school.csv``).
  Model: SIR, dS/dt = -beta S I / N, dI/dt = beta S I / N - gamma I, dR/dt = gamma I (N = 763), beta and gamma
  uncertain; only I measured (S = 762, I = 1, R = 0 on day 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import torch

from .._errors import InputError
from ..data import Trajectories
from ..systems import MisspecifiedSystem

__all__ = ["Dataset", "load", "names"]

#: The fixed predator-conversion rate of the ``lynx`` model (per year per unit of hares): the hares are not
#: measured, so their unit is a choice; this one puts them near the lynx counts' own size.
LYNX_CONVERSION = 1e-3
#: The boarding school's population (the ``influenza`` model's N).
SCHOOL_SIZE = 763.0


@dataclass(frozen=True)
class Dataset:
    """One public data set with its model.

    Attributes:
        name: the key of :func:`load`.
        trajectories: the measurements (float64); NaN where a state was not measured.
        system: the model as a scientist writes it: G with its uncertain parameters (Gaussian priors), no true
            correction.
        citation: where the numbers come from.
        description: one line: what was measured, in which units, and the model.
        noise: ``"relative"`` (positive measurements with multiplicative errors: compare logs) or ``"counts"``
            (counts that may be small: compare ``log(1 + y)``).
    """

    name: str
    trajectories: Trajectories
    system: MisspecifiedSystem
    citation: str
    description: str
    noise: str


# ---- the models' right-hand sides G(y, theta) ------------------------------------------------------------------
def logistic(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """dy/dt = r y (1 - y / K), theta = (r, K)."""
    return theta[0] * y * (1 - y / theta[1])


def monomolecular(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """dh/dt = k (A - h), theta = (k, A)."""
    return theta[0] * (theta[1] - y)


def one_compartment_oral(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """states (gut, conc), theta = (ka, ke, V): d gut/dt = -ka gut, d conc/dt = ka gut / V - ke conc."""
    gut, conc = y[..., 0], y[..., 1]
    ka, ke, volume = theta[0], theta[1], theta[2]
    return torch.stack([-ka * gut, ka * gut / volume - ke * conc], dim=-1)


def lotka_volterra(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """states (hare, lynx), theta = (a, b, c, d): a hare - b hare lynx, d hare lynx - c lynx."""
    hare, lynx = y[..., 0], y[..., 1]
    a, b, c, d = theta[0], theta[1], theta[2], theta[3]
    return torch.stack([a * hare - b * hare * lynx, d * hare * lynx - c * lynx], dim=-1)


def lotka_volterra_fixed_conversion(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """:func:`lotka_volterra` with d = :data:`LYNX_CONVERSION`, theta = (a, b, c)."""
    d = torch.full_like(theta[:1], LYNX_CONVERSION)
    return lotka_volterra(y, torch.cat([theta, d]))


def sir(y: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """states (S, I, R), theta = (beta, gamma), N = :data:`SCHOOL_SIZE`."""
    s, i = y[..., 0], y[..., 1]
    infection = theta[0] * s * i / SCHOOL_SIZE
    recovery = theta[1] * i
    return torch.stack([-infection, infection - recovery, recovery], dim=-1)


# ---- the data sets -----------------------------------------------------------------------------------------------
_SPECS = {
    "orange": dict(
        file="orange.csv",
        columns=dict(time_column="age", experiment_column="tree", state_columns=["circumference"]),
        system=lambda: MisspecifiedSystem(
            logistic,
            1,
            name="orange",
            state_names=["circumference"],
            parameters={"r": (3e-3, 1.5e-3), "K": (200.0, 100.0)},
        ),
        citation="R datasets::Orange; Draper, N. R. and Smith, H. (1981) Applied Regression Analysis, Wiley (exercise "
        "24.N of the 1998 edition, as R's documentation cites it)",
        description="trunk circumference (mm) of 5 orange trees at 7 ages (days); logistic growth, r and K uncertain",
        noise="relative",
    ),
    "loblolly": dict(
        file="loblolly.csv",
        columns=dict(time_column="age", experiment_column="seed", state_columns=["height"]),
        system=lambda: MisspecifiedSystem(
            monomolecular,
            1,
            name="loblolly",
            state_names=["height"],
            parameters={"k": (0.05, 0.025), "A": (90.0, 45.0)},
        ),
        citation="R datasets::Loblolly; Kung, F. H. (1986) Fitting logistic growth curve with predetermined carrying "
        "capacity, ASA Proceedings of the Statistical Computing Section, 340-343",
        description="height (ft) of 14 loblolly pines at 6 ages (years); monomolecular growth, k and A uncertain",
        noise="relative",
    ),
    "chickweight": dict(
        file="chickweight.csv",
        columns=dict(time_column="time", experiment_column="chick", state_columns=["weight"]),
        system=lambda: MisspecifiedSystem(
            logistic, 1, name="chickweight", state_names=["weight"], parameters={"r": (0.1, 0.05), "K": (300.0, 150.0)}
        ),
        citation="R datasets::ChickWeight; Crowder, M. and Hand, D. (1990) Analysis of Repeated Measures, Chapman and "
        "Hall (example 5.3)",
        description="body weight (g) of 50 chicks on 4 diets, days 0-21; logistic growth, r and K uncertain (diet "
        "ignored)",
        noise="relative",
    ),
    "theoph": dict(
        file="theoph.csv",
        columns=dict(time_column="time", experiment_column="subject", state_columns=["gut", "conc"]),
        system=lambda: MisspecifiedSystem(
            one_compartment_oral,
            2,
            name="theoph",
            state_names=["gut", "conc"],
            parameters={"ka": (1.5, 0.75), "ke": (0.08, 0.04), "V": (0.5, 0.25)},
        ),
        citation="R datasets::Theoph; Boeckmann, A. J., Sheiner, L. B. and Beal, S. L. (1994) NONMEM Users Guide: "
        "Part V, NONMEM Project Group, University of California, San Francisco",
        description="theophylline concentration (mg/L) in 12 subjects over 25 h after an oral dose (mg/kg); one "
        "compartment with first-order absorption, ka, ke, V uncertain, gut amount not measured (dose at t = 0)",
        noise="relative",
    ),
    "lynx": dict(
        file="lynx.csv",
        columns=dict(time_column="year", experiment_column=None, state_columns=["lynx"]),
        system=lambda: MisspecifiedSystem(
            lotka_volterra_fixed_conversion,
            2,
            name="lynx",
            state_names=["hare", "lynx"],
            parameters={"a": (0.55, 0.25), "b": (3.7e-4, 1.8e-4), "c": (0.8, 0.4)},
        ),
        citation="R datasets::lynx; Brockwell, P. J. and Davis, R. A. (1991) Time Series and Forecasting Methods, "
        "2nd ed., Springer (series G); Campbell, M. J. and Walker, A. M. (1977) JRSS A 140, 411-431",
        description="annual Canadian lynx trappings 1821-1934 (counts), one trajectory; Lotka-Volterra with the hares "
        "unmeasured, a, b, c uncertain",
        noise="counts",
    ),
    "hare_lynx": dict(
        file="hare_lynx.csv",
        columns=dict(time_column="year", experiment_column=None, state_columns=["hare", "lynx"]),
        system=lambda: MisspecifiedSystem(
            lotka_volterra,
            2,
            name="hare_lynx",
            state_names=["hare", "lynx"],
            parameters={"a": (0.55, 0.25), "b": (0.028, 0.014), "c": (0.8, 0.4), "d": (0.024, 0.012)},
        ),
        citation="Hudson's Bay Company pelts: Hewitt, C. G. (1921) The Conservation of the Wild Life of Canada, "
        "Scribner; Odum, E. P. (1953) Fundamentals of Ecology, Saunders; tabulated by Howard, P. (2009) Modeling "
        "basics, lecture notes, Texas A&M; file stan-dev/example-models knitr/lotka-volterra/hudson-bay-lynx-hare.csv",
        description="hare and lynx pelts (thousands) 1900-1920, one trajectory; Lotka-Volterra, its 4 rates uncertain",
        noise="relative",
    ),
    "influenza": dict(
        file="influenza.csv",
        columns=dict(time_column="day", experiment_column=None, state_columns=["S", "I", "R"]),
        system=lambda: MisspecifiedSystem(
            sir, 3, name="influenza", state_names=["S", "I", "R"], parameters={"beta": (2.0, 1.0), "gamma": (0.5, 0.25)}
        ),
        citation='Anonymous (1978) "Influenza in a boarding school", British Medical Journal 1, 587 (4 March); '
        "R outbreaks::influenza_england_1978_school; file epirecipes/Outbreaks.jl "
        "data/influenza_england_1978_school.csv",
        description="boys in bed (of 763) on days 1-14 of an influenza outbreak, one trajectory; SIR, beta and gamma "
        "uncertain, only I measured (S, I, R given on day 0)",
        noise="counts",
    ),
}


def names() -> list[str]:
    """The data sets :func:`load` knows, in a fixed order."""
    return list(_SPECS)


def _trajectories(spec: dict, system: MisspecifiedSystem) -> Trajectories:
    """The packaged CSV read by :meth:`Trajectories.load`; states of the model that no column holds (the lynx
    model's hares) are added as NaN columns, in the model's order."""
    path = resources.files(__package__) / "data" / spec["file"]
    with resources.as_file(path) as file:
        data = Trajectories.load(file, **spec["columns"])
    if data.state_names == system.state_names:
        return data
    columns = list(data.state_names)
    nan = torch.full_like(data.states[..., :1], float("nan"))
    states = torch.cat([data.states[..., [columns.index(n)]] if n in columns else nan for n in system.state_names], -1)
    return Trajectories(data.times, states, state_names=system.state_names)


def load(name: str) -> Dataset:
    """The data set ``name`` (one of :func:`names`) with its model; read from the package's CSV, nothing downloaded."""
    if not isinstance(name, str) or name not in _SPECS:
        raise InputError(
            f"name: expected one of {names()}, got {name!r:.80}; list them with torchmisspec.datasets.names()"
        )
    spec = _SPECS[name]
    system = spec["system"]()
    return Dataset(
        name=name,
        trajectories=_trajectories(spec, system),
        system=system,
        citation=spec["citation"],
        description=spec["description"],
        noise=spec["noise"],
    )
