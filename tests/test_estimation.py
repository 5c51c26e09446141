import pytest
import torch

from fgat.optics.estimation import OpticsEstimation, run_event
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.phantoms import beads

DEPTHS = [-9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0]


def aberrated_case():
    system = load_system("small")
    truth = torch.from_numpy(beads((7, 32, 32), 8, sigma=1.0, min_spacing=5, margin=(0, 4, 4), seed=2))
    with torch.no_grad():
        true_psf = JPGM.with_parameters(system, DEPTHS, zernike={5: 0.15, 6: -0.1}, intercepts={1: [0.0, 0.8]})()
    measurement = FLFMOperator(true_psf, truth.shape).forward(truth)
    return system, truth, measurement


@pytest.mark.parametrize("estimate,moved", [("zernike", {"zernike_coefficients"}), ("shifts", {"intercepts", "slopes"})])
def test_one_event_lowers_the_data_loss_and_moves_only_its_parameters(estimate, moved):
    system, truth, measurement = aberrated_case()
    jpgm = JPGM(system, DEPTHS)
    schedule = OpticsEstimation(estimate=estimate, steps=8, lr_zernike=0.02, lr_intercepts=0.1)
    result = run_event(jpgm, truth, measurement, schedule, schedule.optimizer(jpgm))
    assert result["loss_after"] < 0.9 * result["loss_before"]
    for name in ("zernike_coefficients", "intercepts", "slopes"):
        changed = bool(getattr(jpgm, name).detach().abs().max() > 0)
        assert changed == (name in moved), name
    if estimate == "zernike":  # moves towards the truth: c5 up, c6 down
        c = dict(zip(jpgm.zernike_indices, jpgm.zernike_coefficients.detach().tolist()))
        assert c[5] > 0 and c[6] < 0
    else:
        assert jpgm.intercepts.detach()[1, 1] > 0


def test_schedule():
    schedule = OpticsEstimation(estimate="joint", start=200, every=50)
    assert [k for k in range(0, 401) if schedule.due(k)] == [250, 300, 350, 400]  # Table S7's note
    assert not OpticsEstimation().enabled and not OpticsEstimation().due(250)
    with pytest.raises(ValueError, match="optics.estimate must be one of"):
        OpticsEstimation(estimate="pupil")


def test_command_line_strings_are_coerced():
    from fgat.gaussians.densify import DensificationStrategy

    assert OpticsEstimation(estimate="joint", start="50", steps="5", lr_zernike="1e-3").lr_zernike == 1e-3
    assert DensificationStrategy(enabled="false").enabled is False
    with pytest.raises(ValueError, match="steps must be an integer, got 'many'"):
        OpticsEstimation(steps="many")
