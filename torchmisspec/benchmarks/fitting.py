"""``scripts/benchmark.py --only fit`` and ``--only gradient``: CorrectionGP's fit against stock GPyTorch and
scikit-learn, and the analytic marginal-likelihood gradient against autograd through the Cholesky (the page is
written by :mod:`torchmisspec.benchmarks.page`)."""

from __future__ import annotations

import math
import warnings

import torch

import torchmisspec as tms
from torchmisspec.design.candidates import uniform_box
from torchmisspec.gp import _mll

from .reporting import timed

# L-BFGS settings of CorrectionGP.fit (torchmisspec/gp/_optim.py), used by every torch.optim.LBFGS loop below
LBFGS = {
    "lr": 1.0,
    "history_size": 20,
    "line_search_fn": "strong_wolfe",
    "tolerance_grad": 1e-7,
    "tolerance_change": 1e-12,
}
MAX_ITER = 200  # CorrectionGP's default max_iter
EXACT_CHOLESKY_SIZE = 10**5


def correction_data(n_traj: int, n_times: int, seed: int = 0):
    """paper_linear, ``n_traj`` random trajectories x ``n_times`` times on [0, 6]: the system and its correction
    samples (oracle derivatives, noise std 1e-2)."""
    system = tms.systems.paper_linear()
    gen = torch.Generator().manual_seed(seed)
    times = torch.linspace(0.0, 6.0, n_times, dtype=torch.float64)
    trajs = tms.simulate(system, uniform_box(n_traj, system.domain, generator=gen), times)
    return system, tms.correction_samples(trajs, system, derivative="oracle", noise_std=1e-2, generator=gen)


def _exact_lml(X, Y, lengthscale: float, outputscale: float, noise_variance: float) -> float:
    """Our exact log marginal likelihood (nats, both outputs) at given hyperparameters: the common yardstick."""
    fixed = tms.CorrectionGP(lengthscale=lengthscale, outputscale=outputscale, noise_variance=noise_variance)
    return fixed.fit(X, Y).log_marginal_likelihood_


def _start_values(X: torch.Tensor, Y: torch.Tensor) -> dict:
    """The starting values CorrectionGP.fit uses (its public ``starting_values`` hook), so the peers start there too."""
    return {k: float(v) for k, v in tms.CorrectionGP().starting_values(X, Y).items()}


def _modules(start: dict):
    """A fresh shared RBF ScaleKernel and GaussianLikelihood (float64), the modules CorrectionGP builds
    (``CorrectionGP().covar_module`` / ``.likelihood``: log-space positive constraints), set to ``start``."""
    gp = tms.CorrectionGP()
    covar, lik = gp.covar_module, gp.likelihood
    with torch.no_grad():
        # tensors of the modules' dtype: GPyTorch's setters would round a Python float through float32
        covar.base_kernel.lengthscale = torch.full_like(covar.base_kernel.lengthscale, start["lengthscale"])
        covar.outputscale = torch.full_like(covar.outputscale, start["outputscale"])
        lik.noise = torch.full_like(lik.noise, start["noise_variance"])
    covar.requires_grad_(True)  # CorrectionGP keeps its parameters frozen outside its own fit; a peer trains them
    lik.requires_grad_(True)
    return covar, lik


def _hyperparameters(covar, lik) -> dict:
    return {
        "lengthscale": float(covar.base_kernel.lengthscale.detach().reshape(-1)[0]),
        "outputscale": float(covar.outputscale.detach().reshape(-1)[0]),
        "noise_variance": float(lik.noise.detach().reshape(-1)[0]),
    }


def _raw_parameters(covar, lik) -> list[torch.Tensor]:
    return [covar.base_kernel.raw_lengthscale, covar.raw_outputscale, lik.noise_covar.raw_noise]


# ------------------------------------------------------------------------------------------------------- fit
def _gpytorch_fit(X: torch.Tensor, Y: torch.Tensor, start: dict, exact: bool) -> dict:
    """Stock GPyTorch training: ExactGP (the d_out outputs as a batch of independent GPs sharing one kernel),
    ExactMarginalLogLikelihood, torch.optim.LBFGS (strong Wolfe, CorrectionGP's settings) on all three raw
    hyperparameters from the same start. ``exact``: max_cholesky_size(10**5), else GPyTorch's defaults."""
    import gpytorch
    from gpytorch.utils.warnings import NumericalWarning

    class PeerGP(gpytorch.models.ExactGP):
        def __init__(self, train_x, train_y, likelihood, covar_module):
            super().__init__(train_x, train_y, likelihood)  # train_y (d_out, N): a batch of d_out GPs
            self.mean_module = gpytorch.means.ZeroMean(batch_shape=torch.Size([train_y.shape[0]]))
            self.covar_module = covar_module

        def forward(self, x):
            covar = self.covar_module(x)  # one kernel, shared by the batch
            return gpytorch.distributions.MultivariateNormal(
                self.mean_module(x), covar.expand(self.train_targets.shape[0], *covar.shape)
            )

    covar, lik = _modules(start)
    model = PeerGP(X, Y.T.contiguous(), lik, covar).train()
    lik.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(lik, model)
    opt = torch.optim.LBFGS(list(model.parameters()), max_iter=MAX_ITER, **LBFGS)
    n, d_out = Y.shape
    count = {"evaluations": 0}

    def closure():
        opt.zero_grad()
        loss = -mll(model(X), model.train_targets).mean()  # = -log p / (N d_out), as CorrectionGP normalises
        loss.backward()
        count["evaluations"] += 1
        return loss

    torch.manual_seed(0)  # CG / Lanczos draw random probe vectors: the same ones in every repeat
    size = EXACT_CHOLESKY_SIZE if exact else gpytorch.settings.max_cholesky_size.value()
    with warnings.catch_warnings(record=True) as caught, gpytorch.settings.max_cholesky_size(size):
        warnings.simplefilter("always", NumericalWarning)
        opt.step(closure)

    def own_lml() -> float:
        """GPyTorch's own value of log p at the final hyperparameters (same settings and seed), not timed."""
        torch.manual_seed(0)
        with torch.no_grad(), warnings.catch_warnings(), gpytorch.settings.max_cholesky_size(size):
            warnings.simplefilter("ignore", NumericalWarning)
            return float(mll(model(X), model.train_targets).sum()) * n

    return {
        "iterations": int(opt.state[opt._params[0]].get("n_iter", 0)),
        "evaluations": count["evaluations"],
        "hyperparameters": _hyperparameters(covar, lik),
        "max_cholesky_size": size,
        "numerical_warnings": sum(issubclass(w.category, NumericalWarning) for w in caught),
        "own_lml": own_lml,  # replaced by its value after timing
    }


def _sklearn_fit(X: torch.Tensor, Y: torch.Tensor):
    """scikit-learn's GPR with its default optimizer (scipy L-BFGS-B, jac=True, no restarts), counting its work."""
    import scipy.optimize
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    count = {}

    def optimizer(obj_func, initial_theta, bounds):  # what GaussianProcessRegressor(optimizer="fmin_l_bfgs_b") does
        res = scipy.optimize.minimize(obj_func, initial_theta, method="L-BFGS-B", jac=True, bounds=bounds)
        count.update(iterations=int(res.nit), evaluations=int(res.nfev))
        return res.x, res.fun

    kernel = ConstantKernel(1.0) * RBF(1.0) + WhiteKernel(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ConvergenceWarning when a hyperparameter sits at its bound
        sk = GaussianProcessRegressor(kernel, alpha=0.0, optimizer=optimizer).fit(X.numpy(), Y.numpy())
    return sk, count


def bench_fit(smoke: bool, repeats: int) -> dict:
    n_traj, n_times = (20, 10) if smoke else (200, 10)
    _, samples = correction_data(n_traj, n_times)
    X, Y = samples.inputs, samples.targets
    start = _start_values(X, Y)
    out = {
        "N": X.shape[0],
        "trajectories": n_traj,
        "times_per_trajectory": n_times,
        "d_in": X.shape[1],
        "d_out": Y.shape[1],
        "start": start,
    }

    gp, t, all_t = timed(lambda: tms.CorrectionGP().fit(X, Y), repeats)
    hp = {"lengthscale": gp.lengthscale, "outputscale": gp.outputscale, "noise_variance": gp.noise_variance}
    out["ours"] = {
        "seconds": t,
        "all_seconds": all_t,
        "lml": gp.log_marginal_likelihood_,
        "iterations": gp.n_iterations_,
        "evaluations": gp.n_evaluations_,
        "hyperparameters": hp,
    }
    for name, exact in (("gpytorch_default", False), ("gpytorch_cholesky", True)):
        res, t, all_t = timed(lambda exact=exact: _gpytorch_fit(X, Y, start, exact), repeats)
        res["own_lml"] = res["own_lml"]()
        out[name] = {"seconds": t, "all_seconds": all_t, "lml": _exact_lml(X, Y, **res["hyperparameters"]), **res}

    (sk, count), t, all_t = timed(lambda: _sklearn_fit(X, Y), repeats)
    params = sk.kernel_.get_params()
    sk_hp = {
        "lengthscale": float(params["k1__k2__length_scale"]),
        "outputscale": float(params["k1__k1__constant_value"]),
        "noise_variance": float(params["k2__noise_level"]),
    }
    out["sklearn"] = {
        "seconds": t,
        "all_seconds": all_t,
        "lml": _exact_lml(X, Y, **sk_hp),
        "own_lml": float(sk.log_marginal_likelihood_value_),
        **count,
        "hyperparameters": sk_hp,
        "kernel": str(sk.kernel_),
    }
    ours = out["ours"]
    for peer in ("gpytorch_default", "gpytorch_cholesky", "sklearn"):
        p = out[peer]
        p["time_ratio"] = ours["seconds"] / p["seconds"]  # ours / peer
        p["lml_relative_gap"] = (p["lml"] - ours["lml"]) / abs(p["lml"])  # negative: ours is higher
    return out


# -------------------------------------------------------------------------------------------------- gradient
def _value_and_surrogate(covar, lik, X, Yb, gradient: str):
    """The exact log marginal likelihood of a shared kernel and a scalar whose gradient is its gradient.

    ``"analytic"``: the package's route (factorize without a graph, Q, the O(N^2) surrogate);
    ``"autograd"``: the value itself, built through torch.linalg.cholesky + cholesky_solve + logdet.
    """
    K = covar.forward(X, X).unsqueeze(0)  # (1, N, N)
    diag = lik.noise.reshape(1, 1)
    if gradient == "analytic":
        with torch.no_grad():
            fac = _mll.factorize(K.detach(), diag.detach(), Yb, warn=False)
            value = _mll.exact_mll(fac, X.shape[0])
            Q = _mll.gradient_weights(fac)
        return value, _mll.gradient_surrogate(Q, K, diag)
    C = K + diag.unsqueeze(-1) * torch.eye(X.shape[0], dtype=K.dtype)
    L = torch.linalg.cholesky(C)
    alpha = torch.cholesky_solve(Yb, L)
    logdet = 2.0 * L.diagonal(dim1=-2, dim2=-1).log().sum()
    _, n, m = Yb.shape
    value = -0.5 * (Yb * alpha).sum() - 0.5 * m * logdet - 0.5 * n * m * math.log(2 * math.pi)
    return value, value


def _value_and_gradient(covar, lik, X, Yb, gradient: str):
    params = _raw_parameters(covar, lik)
    for p in params:
        p.grad = None
    value, surrogate = _value_and_surrogate(covar, lik, X, Yb, gradient)
    surrogate.backward()
    return float(value.detach()), torch.cat([p.grad.reshape(-1) for p in params])


def _time_gradient(covar, lik, X, Yb, gradient: str, evals: int):
    _value_and_gradient(covar, lik, X, Yb, gradient)  # warm-up
    return timed(lambda: _value_and_gradient(covar, lik, X, Yb, gradient), evals)


def _lbfgs_fit(X, Y, start: dict, gradient: str) -> dict:
    """L-BFGS (CorrectionGP's settings) on the exact likelihood over lengthscale, outputscale and noise (log space,
    no profiling, no warm start) with either gradient: the gradient trick alone, inside a whole fit."""
    covar, lik = _modules(start)
    params = _raw_parameters(covar, lik)
    opt = torch.optim.LBFGS(params, max_iter=MAX_ITER, **LBFGS)
    Yb = Y.unsqueeze(0)
    norm = float(Y.numel())
    count = [0]

    def closure():
        opt.zero_grad()
        value, surrogate = _value_and_surrogate(covar, lik, X, Yb, gradient)
        (-surrogate / norm).backward()
        count[0] += 1
        return -value.detach() / norm

    opt.step(closure)
    return {
        "iterations": int(opt.state[opt._params[0]].get("n_iter", 0)),
        "evaluations": count[0],
        "hyperparameters": _hyperparameters(covar, lik),
    }


def bench_gradient(smoke: bool, repeats: int) -> dict:
    sizes = (100, 200) if smoke else (500, 1000, 2000)
    evals = max(3, repeats) if smoke else max(5, repeats)
    out = {"sizes": [], "evaluation_repeats": evals}
    for n in sizes:
        _, samples = correction_data(n // 10, 10)
        X, Y = samples.inputs, samples.targets
        start = _start_values(X, Y)
        covar, lik = _modules(start)
        row = {"N": X.shape[0], "d_in": X.shape[1], "d_out": Y.shape[1], "hyperparameters": start}
        results = {}
        for gradient in ("analytic", "autograd"):
            (value, grad), t, all_t = _time_gradient(covar, lik, X, Y.unsqueeze(0), gradient, evals)
            results[gradient] = (value, grad)
            row[f"{gradient}_seconds"] = t
            row[f"{gradient}_all_seconds"] = all_t
        (va, ga), (vb, gb) = results["analytic"], results["autograd"]
        row["value_relative_difference"] = abs(va - vb) / abs(vb)
        row["gradient_max_relative_difference"] = float(((ga - gb).abs() / gb.abs()).max())
        row["gradient"] = gb.tolist()
        row["speedup"] = row["autograd_seconds"] / row["analytic_seconds"]  # the docs claimed 3-4x
        out["sizes"].append(row)

    n_traj = 20 if smoke else 200
    _, samples = correction_data(n_traj, 10)
    X, Y = samples.inputs, samples.targets
    start = _start_values(X, Y)
    fits = {"N": X.shape[0], "start": start}
    for gradient in ("analytic", "autograd"):
        res, t, all_t = timed(lambda gradient=gradient: _lbfgs_fit(X, Y, start, gradient), repeats)
        fits[gradient] = {
            "seconds": t,
            "all_seconds": all_t,
            "lml": _exact_lml(X, Y, **res["hyperparameters"]),
            "seconds_per_evaluation": t / res["evaluations"],
            **res,
        }
    fits["speedup"] = fits["autograd"]["seconds"] / fits["analytic"]["seconds"]
    fits["speedup_per_evaluation"] = (
        fits["autograd"]["seconds_per_evaluation"] / fits["analytic"]["seconds_per_evaluation"]
    )
    fits["library"] = timed(lambda: tms.CorrectionGP().fit(X, Y), repeats)[1]  # profiled + warm start
    out["fit"] = fits
    return out
