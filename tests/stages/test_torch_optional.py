"""The optional torch paths: TorchScript consumer and the torch SGRA loss (skipped without torch)."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gtforge.predictors import InputConvention, TorchScriptModel  # noqa: E402
from gtforge.training import sgra_loss, sgra_loss_torch  # noqa: E402


class ShiftNet(torch.nn.Module):
    """Disparity = 10 + mean of the left image's first channel (so inputs matter), as (N, H, W)."""

    def forward(self, left, right):
        return 10.0 + left[:, 0].mean() * 0.0 + (right[:, 0] * 0.0)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch 2.13 deprecates TorchScript; users still ship it
def test_torchscript_model_pads_and_crops(tmp_path):
    path = tmp_path / "m.pt"
    torch.jit.script(ShiftNet()).save(str(path))
    m = TorchScriptModel(path, InputConvention())
    left = np.zeros((50, 70, 3), np.uint8)
    d = m.predict("x", left, left)
    assert d.shape == (50, 70) and np.allclose(d, 10.0)


def test_torch_sgra_loss_matches_numpy():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 50, (20, 30))
    gt[0, :5] = np.nan
    w = rng.choice([0.0, 0.8, 1.0, 1.4], size=gt.shape)
    init = gt + rng.normal(0, 2, gt.shape)
    resid = gt + rng.normal(0, 0.5, gt.shape)
    ref = sgra_loss(init, resid, gt, w, 0.3, 1.0)
    t = {k: torch.tensor(v) for k, v in dict(init=init, resid=resid, gt=gt, w=w).items()}
    got = sgra_loss_torch(t["init"], t["resid"], t["gt"], t["w"], 0.3, 1.0)
    assert float(got) == pytest.approx(ref, rel=1e-9)
    w[1, 1] = 1.0
    resid[1, 1] = np.nan  # a diverged pixel where the label counts: NaN in both
    got = sgra_loss_torch(t["init"], torch.tensor(resid), t["gt"], torch.tensor(w), 0.3, 1.0)
    assert np.isnan(float(got)) and np.isnan(sgra_loss(init, resid, gt, w, 0.3, 1.0))


def test_torch_export_program(tmp_path):
    ex = torch.export.export(ShiftNet(), (torch.zeros(1, 3, 64, 96), torch.zeros(1, 3, 64, 96)))
    torch.export.save(ex, str(tmp_path / "m.pt2"))
    m = TorchScriptModel(tmp_path / "m.pt2", InputConvention())
    left = np.zeros((50, 70, 3), np.uint8)  # padded to 64x96, as exported
    d = m.predict("x", left, left)
    assert d.shape == (50, 70) and np.allclose(d, 10.0)
