"""Known input signals u(t) of experiments (a dilution rate, a dose, a temperature profile): :class:`Controls`.

A lab sets some inputs of its system over time and records them. The package calls them *controls* (the
correction's own inputs x are already called inputs) and takes them as samples of each experiment's profile,
``u_k(t)`` at knots ``s_k1 < s_k2 < ...``, with an interpolation rule the user states:

* ``"previous"`` (zero-order hold, the default): ``u(t) = u(s_j)`` for ``s_j <= t < s_{j+1}``, a piecewise-constant
  profile as a pump or a heater set at discrete times produces; the solver is told where the jumps are
  (torchdiffeq's ``jump_t``), so the steps never straddle one;
* ``"linear"``: linear interpolation between the knots.

Before the first knot and after the last, the profile keeps its first / last value. A callable ``u(t)``, the same
profile for every experiment, is accepted too
(:meth:`Controls.from_function <torchmisspec.signals.Controls.from_function>`). Every evaluation is vectorised over
the experiments, so a batch of experiments with different profiles is still one solve.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from ._errors import InputError, ShapeError
from ._user_code import call_user
from ._validation import NotATensor, as_tensor, check_names, check_positive_int, check_selection, check_to

__all__ = ["KINDS", "Controls"]

#: the interpolation rules of sampled profiles
KINDS = ("previous", "linear")


class Controls(NotATensor):
    """The known input profiles of K experiments.

    ``Controls(knots, values, kind="previous")``:

    * ``knots``: ``(S,)`` shared by the experiments, ``(K, S)``, or a list of K ``(S_k,)`` arrays (each strictly
      increasing; one knot is a constant profile);
    * ``values``: ``(K, S, m)`` or a list of K ``(S_k, m)`` arrays (``(K, S)`` / ``(S_k,)`` for one control);
    * ``kind``: ``"previous"`` (piecewise constant) or ``"linear"``;
    * ``names``: the m controls' names (default ``u0, u1, ...``).

    Values must be finite: a control is known (a missing cell of a lab's table is an error, not a gap).
    """

    def __init__(self, knots, values, *, kind: str = "previous", names: Sequence[str] | None = None) -> None:
        if not (isinstance(kind, str) and kind in KINDS):
            raise InputError(f"kind: expected one of {KINDS} (how the profile runs between its samples), got {kind!r}")
        self.kind = kind
        self._function = None
        if isinstance(values, (list, tuple)):
            vals = [as_tensor(v, f"values[{k}]") for k, v in enumerate(values)]
            vals = [v.unsqueeze(-1) if v.dim() == 1 else v for v in vals]
            if not vals or any(v.dim() != 2 for v in vals) or len({v.shape[-1] for v in vals}) != 1:
                raise ShapeError(
                    f"values: expected a non-empty list of (S_k, m) arrays, got shapes {[tuple(v.shape) for v in vals]}"
                )
            if isinstance(knots, (list, tuple)) and knots and isinstance(knots[0], (list, tuple, torch.Tensor)):
                if len(knots) != len(vals):
                    raise ShapeError(f"knots: expected {len(vals)} knot arrays (one per experiment), got {len(knots)}")
                kn = [as_tensor(t, f"knots[{k}]", dtype=vals[k].dtype) for k, t in enumerate(knots)]
            else:
                shared = as_tensor(knots, "knots", dtype=vals[0].dtype)
                kn = [shared] * len(vals)
            if len(kn) != len(vals):
                raise ShapeError(f"knots: expected {len(vals)} knot arrays (one per experiment), got {len(kn)}")
            lengths = [v.shape[0] for v in vals]
            S = max(lengths)
            for k, (t, v) in enumerate(zip(kn, vals, strict=True)):
                if t.dim() != 1 or t.shape[0] != v.shape[0]:
                    raise ShapeError(
                        f"knots[{k}]: expected ({v.shape[0]},) times, one per value row, got shape {tuple(t.shape)}"
                    )
            knots_t = torch.stack([torch.cat([t, t[-1:].expand(S - t.shape[0])]) for t in kn])
            values_t = torch.stack([torch.cat([v, v[-1:].expand(S - v.shape[0], -1)]) for v in vals])
            self.lengths = torch.tensor(lengths)
        else:
            values_t = as_tensor(values, "values")
            if values_t.dim() == 2:
                values_t = values_t.unsqueeze(-1)
            if values_t.dim() != 3:
                raise ShapeError(
                    f"values: expected (K, S, m) samples of the controls, got shape {tuple(values_t.shape)}"
                )
            knots_t = as_tensor(knots, "knots", dtype=values_t.dtype, device=values_t.device)
            if knots_t.dim() == 1:
                knots_t = knots_t.expand(values_t.shape[0], -1)
            if knots_t.shape != values_t.shape[:2]:
                raise ShapeError(
                    f"knots: expected ({values_t.shape[1]},) or {tuple(values_t.shape[:2])} to match values "
                    f"{tuple(values_t.shape)}, got shape {tuple(knots_t.shape)}"
                )
            self.lengths = torch.full((values_t.shape[0],), values_t.shape[1])
        if values_t.shape[0] < 1 or values_t.shape[1] < 1 or values_t.shape[2] < 1:
            raise ShapeError(f"values: expected at least one experiment, knot and control, got {tuple(values_t.shape)}")
        if not bool(torch.isfinite(values_t).all()) or not bool(torch.isfinite(knots_t).all()):
            raise InputError(
                "values: expected finite control values and knots (a control is known: fill or drop the empty cells), "
                "got NaN or inf"
            )
        steps = knots_t.diff(dim=-1)
        inside = torch.arange(1, knots_t.shape[1], device=steps.device) < self.lengths.unsqueeze(-1).to(steps.device)
        if bool((steps[inside] <= 0).any()):
            k, i = (int(v) for v in ((steps <= 0) & inside).nonzero()[0])
            raise InputError(
                "knots: expected strictly increasing times in every experiment's profile, got "
                f"{float(knots_t[k, i]):g} then {float(knots_t[k, i + 1]):g} in experiment {k}"
            )
        self.knots = knots_t.contiguous()
        self.values = values_t.contiguous()
        self.names = check_names(names, values_t.shape[-1], "names", default="u")

    @classmethod
    def from_function(
        cls, function: Callable[[torch.Tensor], torch.Tensor], num_experiments: int, num_controls: int, **kw
    ) -> Controls:
        """The same profile ``u(t)`` for ``num_experiments`` experiments: ``function`` maps times ``(...,)`` to
        ``(..., m)`` (vectorised; checked at the first call)."""
        if not callable(function):
            raise InputError(f"function: expected a callable u(t), got {type(function).__name__}")
        num_experiments = check_positive_int(num_experiments, "num_experiments")
        num_controls = check_positive_int(num_controls, "num_controls")
        zeros = torch.zeros(num_experiments, 1, num_controls, dtype=torch.float64)
        out = cls(torch.zeros(1, dtype=torch.float64), zeros, **kw)
        out._function = function
        return out

    # ------------------------------------------------------------------------------------------------------
    @property
    def num_experiments(self) -> int:
        return self.values.shape[0]

    @property
    def num_controls(self) -> int:
        return self.values.shape[-1]

    @property
    def is_function(self) -> bool:
        """Whether the profile is a function u(t)
        (:meth:`from_function <torchmisspec.signals.Controls.from_function>`) rather than samples."""
        return self._function is not None

    @property
    def jumps(self) -> torch.Tensor | None:
        """The times where a piecewise-constant profile jumps (for the solver's ``jump_t``), in any experiment;
        ``None`` otherwise. A knot where the value does not change is no jump: a lab's table repeats the input on
        every row (nlme's Remifentanil: a knot at each of 8 subjects' ~50 sample times, an infusion rate that changes
        once or twice each), and an adaptive solver told of every knot restarted at each of them."""
        if self.kind != "previous" or self._function is not None:
            return None
        return torch.unique(self.knots[:, 1:][self.changes()])

    def changes(self) -> torch.Tensor:
        """``(K, S - 1)``: whether experiment k's value at knot i + 1 differs from its value at knot i (any
        control): where a piecewise-constant profile jumps."""
        return (self.values[:, 1:] != self.values[:, :-1]).any(-1)

    def at(self, t: torch.Tensor) -> torch.Tensor:
        """The controls at times ``t``: a scalar (every experiment at that time) gives ``(K, m)``; ``(K, T)`` gives
        ``(K, T, m)``; any shape ``(K, ...)`` gives ``(K, ..., m)``."""
        t = as_tensor(t, "t", dtype=self.values.dtype, device=self.values.device)
        if self._function is not None:
            tt = t.expand(self.num_experiments) if t.dim() == 0 else t
            out = call_user(self._function, tt, "controls: u(t)")
            want = tuple(tt.shape) + (self.num_controls,)
            if not isinstance(out, torch.Tensor) or tuple(out.shape) != want:
                got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
                raise ShapeError(f"controls: expected u(t) to map times {tuple(tt.shape)} to {want}, got {got}")
            if not bool(torch.isfinite(out).all()):  # a control is known: NaN would run the solve on garbage
                raise InputError("controls: expected u(t) finite at every time (a control is known), got NaN or inf")
            return out.to(self.values)
        K = self.num_experiments
        flat = t.expand(K) if t.dim() == 0 else t
        if flat.shape[0] != K:
            raise ShapeError(f"t: expected a scalar or times (K={K}, ...) for {K} experiments, got {tuple(t.shape)}")
        shape = flat.shape
        q = flat.reshape(K, -1)
        last = (self.lengths.to(q.device) - 1).unsqueeze(-1)
        i = (torch.searchsorted(self.knots, q.contiguous(), right=True) - 1).clamp(min=0)
        i = torch.minimum(i, last)
        v0 = torch.gather(self.values, 1, i.unsqueeze(-1).expand(-1, -1, self.num_controls))
        if self.kind == "previous":
            out = v0
        else:
            j = torch.minimum(i + 1, last)
            t0, t1 = torch.gather(self.knots, 1, i), torch.gather(self.knots, 1, j)
            v1 = torch.gather(self.values, 1, j.unsqueeze(-1).expand(-1, -1, self.num_controls))
            w = ((q - t0) / (t1 - t0).where(j > i, torch.ones_like(t0))).clamp(0, 1).where(j > i, torch.zeros_like(q))
            out = v0 + w.unsqueeze(-1) * (v1 - v0)
        return out.reshape(*shape, self.num_controls)

    def __getitem__(self, index) -> Controls:
        """The profiles of a subset of experiments (int, slice, index list, tensor or boolean mask; at least one)."""
        idx = torch.tensor(check_selection(index, self.num_experiments), dtype=torch.long)
        out = object.__new__(Controls)
        out.kind, out._function, out.names = self.kind, self._function, self.names
        out.knots, out.values, out.lengths = self.knots[idx], self.values[idx], self.lengths[idx]
        return out

    def repeat(self, n: int) -> Controls:
        """These K profiles n times over (``n K`` experiments, as the draws' batch of paths is laid out); ``n >= 1``."""
        return self[torch.arange(self.num_experiments).repeat(check_positive_int(n, "n"))]

    def to(self, *args, **kwargs) -> Controls:
        """These profiles on another device and/or in another real floating dtype."""
        check_to(args, kwargs, "Controls")
        out = self[:]
        out.knots, out.values = self.knots.to(*args, **kwargs), self.values.to(*args, **kwargs)
        out.lengths = self.lengths.to(out.knots.device)
        return out

    def profiles(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``[(knots (S_k,), values (S_k, m)), ...]``: every experiment's samples."""
        return [(self.knots[k, :n], self.values[k, :n]) for k, n in enumerate(self.lengths.tolist())]

    def __len__(self) -> int:
        return self.num_experiments

    def __iter__(self):
        """Each experiment's profile as Controls of one (indexing refuses positions out of range)."""
        return (self[k] for k in range(self.num_experiments))

    def __repr__(self) -> str:
        source = "u(t)" if self._function is not None else f"{int(self.lengths.max())} knots, {self.kind}"
        return f"Controls(K={self.num_experiments}, m={self.num_controls} ({', '.join(self.names)}), {source})"
