"""Model files: exact round trips, and nothing in a file can run code or crash the loader with a foreign error."""

import os

import pytest
import torch

import torchmisspec as tms

DT = torch.float64


class _Payload:
    """An object whose unpickling would create a file (what a malicious model file would do)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.makedirs, (self.marker,))


@pytest.fixture
def fitted():
    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 2, generator=g, dtype=DT)
    # noisy samples: on noiseless ones the learned noise is ~1e-12 and the solve ill-conditioned (alpha ~1e5), so a
    # re-factorization on another thread count moved the mean by ~5e-10, which is round-off, not persistence
    return tms.CorrectionGP().fit(X, torch.sin(3 * X) + 1e-2 * torch.randn(30, 2, generator=g, dtype=DT))


def test_round_trip_is_exact(fitted, tmp_path):
    loaded = tms.CorrectionGP.load(fitted.save(tmp_path / "gp.pt"))
    x = torch.rand(7, 2, generator=torch.Generator().manual_seed(1), dtype=DT)
    # the stored state is exact; the recomputed solve may differ by round-off (thread counts change BLAS orders)
    torch.testing.assert_close(loaded.train_inputs_, fitted.train_inputs_, rtol=0, atol=0)
    torch.testing.assert_close(loaded.train_targets_, fitted.train_targets_, rtol=0, atol=0)
    torch.testing.assert_close(loaded.predict(x).mean, fitted.predict(x).mean, rtol=1e-9, atol=1e-13)
    torch.testing.assert_close(loaded.predict(x).variance, fitted.predict(x).variance, rtol=1e-9, atol=1e-15)
    assert (loaded.lengthscale, loaded.outputscale, loaded.noise_variance) == (
        fitted.lengthscale,
        fitted.outputscale,
        fitted.noise_variance,
    )
    assert loaded.n_evaluations_ == fitted.n_evaluations_


def test_crafted_file_does_not_run_code(fitted, tmp_path):
    path = fitted.save(tmp_path / "gp.pt")
    blob = torch.load(path, weights_only=True)
    marker = tmp_path / "code-ran"
    blob["config"]["kernel"] = _Payload(str(marker))
    torch.save(blob, tmp_path / "evil.pt")
    with pytest.raises(tms.InputError, match="could not be read safely"):
        tms.CorrectionGP.load(tmp_path / "evil.pt")
    assert not marker.exists()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b["config"].__setitem__("dtype", "complex128"), "expected dtype one of"),
        (lambda b: b["config"].__setitem__("kernel", "cubic"), "kernel: expected a Kernel object or one of"),
        (lambda b: b.pop("train_inputs"), "with field 'train_inputs', got fields"),
        (lambda b: b.__setitem__("train_targets", torch.zeros(3, 2, dtype=DT)), "expected training data"),
        (lambda b: b["covar_module"].clear(), "do not match the kernel"),
    ],
)
def test_malformed_files_raise_input_errors(fitted, tmp_path, mutate, message):
    blob = torch.load(fitted.save(tmp_path / "gp.pt"), weights_only=True)
    mutate(blob)
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(tms.InputError, match=message):
        tms.CorrectionGP.load(tmp_path / "bad.pt")


def test_truncated_garbage_and_missing_files(fitted, tmp_path):
    data = fitted.save(tmp_path / "gp.pt").read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "garbage.pt").write_bytes(b"\x00\x01 not a model")
    for name in ("truncated.pt", "garbage.pt"):
        with pytest.raises(tms.InputError, match="could not be read safely"):
            tms.CorrectionGP.load(tmp_path / name)
    with pytest.raises(tms.InputError, match="expected an existing CorrectionGP file"):
        tms.CorrectionGP.load(tmp_path / "missing.pt")
    with pytest.raises(tms.InputError, match="in an existing folder"):
        fitted.save(tmp_path / "no" / "such" / "folder" / "gp.pt")


def test_trajectory_files_are_read_safely(tmp_path):
    import numpy as np

    np.save(tmp_path / "obj.npy", np.array([object()], dtype=object), allow_pickle=True)
    np.savez(tmp_path / "obj.npz", times=np.array([object()], dtype=object), states=np.zeros((1, 1, 1)))
    with pytest.raises(tms.InputError, match="could not be read"):
        tms.Trajectories.load(tmp_path / "obj.npz")
    (tmp_path / "latin.csv").write_bytes("experiment,time,y\xe9\n0,0,1\n".encode("latin-1"))
    with pytest.raises(tms.InputError, match="expected a UTF-8 text CSV file"):
        tms.Trajectories.load(tmp_path / "latin.csv")
    (tmp_path / "long.csv").write_text("experiment,time,y0\n0,0,1\n0,1,2,3\n")
    with pytest.raises(
        tms.ShapeError, match=r"expected 3 columns in every row \(as in the header\), got 4 in data row 2"
    ):
        tms.Trajectories.load(tmp_path / "long.csv")
    (tmp_path / "zip.npz").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(tms.InputError, match="could not be read"):
        tms.Trajectories.load(tmp_path / "zip.npz")
