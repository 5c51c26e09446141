import numpy as np
import pytest
import torch

from fgat.optics.acquisition import MeasuredOperator
from fgat.optics.operator import FLFMOperator
from fgat.optics.psf import JPGM
from fgat.optics.systems import load_system
from fgat.recon.estimation import (
    CPU_DEPTH_CHUNK,
    DepthChunks,
    OpticsEstimation,
    data_loss_backward,
    fitted_update,
    run_event,
)
from fgat.sim.phantoms import beads

DEPTHS = [-9.0, -6.0, -3.0, 0.0, 3.0, 6.0, 9.0]
GAINS = torch.tensor([1.0, 0.9, 0.8, 0.7, 0.75, 0.85, 0.95], dtype=torch.float64)


def aberrated_case():
    system = load_system("small")
    truth = torch.from_numpy(
        beads((7, 32, 32), 8, sigma=1.0, min_spacing=5, margin=(0, 4, 4), seed=2)
    )
    with torch.no_grad():
        true_psf = JPGM.with_parameters(
            system, DEPTHS, zernike={5: 0.15, 6: -0.1}, intercepts={1: [0.0, 0.8]}
        )()
    measurement = FLFMOperator(true_psf, truth.shape).forward(truth)
    return system, truth, measurement


@pytest.mark.parametrize(
    "estimate,moved", [("zernike", {"zernike_coefficients"}), ("shifts", {"intercepts", "slopes"})]
)
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


def test_blurred_events_estimate_their_own_groups():
    """``blurred_estimate``: a blurred event of a joint fit moves only the Zernike coefficients
    (the shifts keep their gradient-free zeros); a sharp one moves every group."""
    system, truth, measurement = aberrated_case()
    schedule = OpticsEstimation(
        estimate="joint", steps=4, lr_zernike=0.02, lr_intercepts=0.1, blurred_estimate="zernike"
    )
    assert schedule.estimated_at(2.0) == ("zernike_coefficients",)
    assert schedule.estimated_at(0.0) == ("zernike_coefficients", "intercepts", "slopes")
    assert OpticsEstimation(estimate="joint").estimated_at(2.0) == schedule.estimated_at(0.0)
    jpgm = JPGM(system, DEPTHS)
    optimizer = schedule.optimizer(jpgm)
    run_event(jpgm, truth, measurement, schedule, optimizer, blur_px=2.0)
    assert jpgm.zernike_coefficients.detach().abs().max() > 0
    assert jpgm.intercepts.detach().abs().max() == 0 and jpgm.slopes.detach().abs().max() == 0
    run_event(jpgm, truth, measurement, schedule, optimizer)
    assert jpgm.intercepts.detach()[1, 1] > 0  # towards the true intercept 0.8 px
    shifts = OpticsEstimation(estimate="shifts", blurred_estimate="zernike")
    assert shifts.estimated_at(2.0) == () and shifts.estimated_at(0.0) == ("intercepts", "slopes")
    with pytest.raises(ValueError, match="leaves the blurred events none of"):
        OpticsEstimation(estimate="shifts", blurred_estimate="zernike", blur_px=(2, 0))
    with pytest.raises(ValueError, match="optics.blurred_estimate must be"):
        OpticsEstimation(estimate="zernike", blurred_estimate="everything")


def test_schedule():
    schedule = OpticsEstimation(estimate="joint", start=200, every=50)
    assert [k for k in range(0, 401) if schedule.due(k)] == [250, 300, 350, 400]  # Table S7's note
    assert not OpticsEstimation().enabled and not OpticsEstimation().due(250)
    with pytest.raises(ValueError, match="optics.estimate must be one of"):
        OpticsEstimation(estimate="pupil")


def test_schedules_of_events_and_densification():
    from fgat.gaussians.densify import Densification

    table_s7 = OpticsEstimation(estimate="joint")  # after step 200, every 50 steps
    assert [step for step in range(1, 401) if table_s7.due(step)] == [250, 300, 350, 400]
    assert not any(OpticsEstimation().due(step) for step in range(1000))  # estimate = none
    densification = Densification(start=100, stop=400, interval=100)
    assert [step for step in range(1000) if densification.due(step)] == [100, 200, 300]
    with pytest.raises(ValueError, match="optics.estimate must be one of"):
        OpticsEstimation(estimate="everything")
    with pytest.raises(
        ValueError, match=r"densification.stop must be >= densification.start \(100\)"
    ):
        Densification(start=100, stop=50)


def test_scene_gauge_removal():
    from fgat.recon.estimation import remove_scene_gauge

    offsets = torch.from_numpy(load_system("small").lenslet_centers_px())
    offsets = offsets - offsets[:1]
    gauge = torch.tensor([0.3, -0.2]) + 0.004 * offsets  # common shift + parallax-like breathing
    torch.testing.assert_close(
        remove_scene_gauge(gauge, offsets),
        torch.zeros(7, 2, dtype=torch.float64),
        atol=1e-12,
        rtol=0,
    )
    tangential = (
        torch.stack([-offsets[:, 1], offsets[:, 0]], dim=1) * 0.01
    )  # a rotation: not a scene change
    torch.testing.assert_close(
        remove_scene_gauge(tangential + gauge, offsets), tangential.double(), atol=1e-12, rtol=0
    )


def test_a_common_intercept_is_a_translated_scene():
    """Why shifts are compared modulo the scene: every view's PSF moved by one pixel gives the
    views of the unshifted optics looking at the scene moved by one pixel the other way."""
    system = load_system("small")
    volume = torch.from_numpy(
        beads((7, 40, 40), 5, sigma=1.0, min_spacing=5, margin=(0, 10, 10), seed=3)
    ).double()
    with torch.no_grad():
        plain = JPGM(system, DEPTHS, dtype=torch.float64)()
        moved = JPGM.with_parameters(
            system, DEPTHS, dtype=torch.float64, intercepts={v: [0.0, 1.0] for v in range(7)}
        )()
    views = FLFMOperator(moved, volume.shape).forward(volume)
    expected = FLFMOperator(plain, volume.shape).forward(torch.roll(volume, -1, dims=2))
    inner = (slice(None), slice(8, -8), slice(8, -8))
    torch.testing.assert_close(
        views[inner], expected[inner], atol=2e-3 * float(expected.max()), rtol=0
    )
    assert float(
        (views - FLFMOperator(plain, volume.shape).forward(volume))[inner].abs().max()
    ) > 0.1 * float(expected.max())  # while the shift itself is large


@pytest.mark.slow
def test_shifts_stopped_by_the_step_budget_are_reported_as_unconverged():
    """A true intercept of 0.8 px: 20 steps of 0.005 px cannot reach it, so the intercept ends at
    lr x steps, still moving at full speed, and the event says so; 60 steps of 0.1 px reach it
    and settle, and nothing is reported."""
    system, truth, measurement = aberrated_case()
    slow = OpticsEstimation(estimate="shifts", steps=20, lr_intercepts=0.005, lr_slopes=0.005)
    jpgm = JPGM(system, DEPTHS)
    result = run_event(jpgm, truth, measurement, slow, slow.optimizer(jpgm))
    assert float(jpgm.intercepts.detach()[1, 1]) == pytest.approx(0.1, abs=0.01)
    assert result["unconverged"]["intercepts"] >= 1
    fast = OpticsEstimation(estimate="shifts", steps=60, lr_intercepts=0.1, lr_slopes=0.1)
    jpgm = JPGM(system, DEPTHS)
    result = run_event(jpgm, truth, measurement, fast, fast.optimizer(jpgm))
    assert "intercepts" not in result["unconverged"]


def test_plateau_of_the_inner_steps():
    from fgat.recon.estimation import plateaued

    assert not plateaued([1.0, 0.5, 0.4], window=2, tolerance=0.0)  # off
    assert not plateaued([1.0, 0.5], window=2, tolerance=0.1)  # too few steps
    assert plateaued([1.0, 0.99, 0.95, 0.94], window=2, tolerance=0.1)  # 0.99 -> 0.94: 5%
    assert not plateaued([1.0, 0.99, 0.80, 0.70], window=2, tolerance=0.1)  # 0.99 -> 0.70


def test_events_stop_their_inner_steps_on_a_plateau():
    system, truth, measurement = aberrated_case()
    runs = {}
    for tolerance in (0.0, 0.5):
        schedule = OpticsEstimation(
            estimate="zernike", steps=12, lr_zernike=0.02, tolerance=tolerance
        )
        jpgm = JPGM(system, DEPTHS)
        runs[tolerance] = (
            run_event(jpgm, truth, measurement, schedule, schedule.optimizer(jpgm)),
            jpgm,
        )
    full, early = runs[0.0][0], runs[0.5][0]
    assert full["steps"] == 12 and not full["quiet"]
    # a window of 3 steps improving by less than half: stops after 4 steps
    assert early["steps"] == 4 and early["loss_after"] < early["loss_before"]
    with pytest.raises(ValueError, match=r"optics.tolerance must be a number in \[0, 1\)"):
        OpticsEstimation(tolerance=1.5)


@pytest.mark.parametrize("method", ["mft", "asm"])
def test_depth_chunked_gradient_is_the_whole_stacks(method):
    """A JPGM inner step in depth chunks (prediction without a graph, each chunk's PSFs
    recomputed with theirs) gives the whole stack's loss and gradient, in float64, for the
    Zernike coefficients, intercepts and slopes; a chunk of the stack is computed alone as it
    is within the whole."""
    system, truth, measurement = aberrated_case()
    volume, measurement = truth.double(), measurement.double()
    mask = torch.ones_like(measurement)
    mask[2, 5:9, 5:9] = 0
    jpgm = JPGM(system, DEPTHS, method=method, dtype=torch.float64)
    with torch.no_grad():
        jpgm.zernike_coefficients[:3] = torch.tensor([0.05, -0.02, 0.03])
        jpgm.slopes[2] = torch.tensor([0.3, -0.2])
    for name, parameter in jpgm.named_parameters():
        parameter.requires_grad_(True)

    def operator(psf):
        return MeasuredOperator(psf, measurement.shape[1:], 0, GAINS)

    def gradient(chunk):
        jpgm.zero_grad(set_to_none=True)
        loss = data_loss_backward(jpgm, operator, volume, measurement, 1, mask, chunk)
        return loss, [parameter.grad.clone() for parameter in jpgm.parameters()]

    whole_loss, whole = gradient(0)
    for chunk in (1, 3):
        loss, chunked = gradient(chunk)
        assert float(loss) == pytest.approx(float(whole_loss), rel=1e-12)
        for expected, actual in zip(whole, chunked):
            assert expected.abs().max() > 0
            torch.testing.assert_close(actual, expected, rtol=1e-9, atol=1e-12)
    with torch.no_grad():
        torch.testing.assert_close(jpgm(slice(2, 5)), jpgm()[:, 2:5], rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="depths must be a non-empty slice of the 7 planes"):
        jpgm(slice(7, 9))
    with pytest.raises(ValueError, match="optics.depth_chunk must be a number of depths >= 0"):
        OpticsEstimation(depth_chunk=-1)
    with pytest.raises(ValueError, match="or 'auto', got 'whole'"):
        OpticsEstimation(depth_chunk="whole")


def test_auto_depth_chunks_halve_until_an_update_fits():
    """``depth_chunk="auto"`` on a GPU starts with the whole stack and, each time an update
    runs out of memory, retries it with half as many depths per chunk: here a device that holds
    the graph of at most 2 depths, so 7 -> 4 -> 2, with the whole stack's loss and gradient
    (float64) and the size kept for the next update. A fixed setting raises instead; on a CPU
    "auto" is chunks of CPU_DEPTH_CHUNK depths (the whole stack when it has no more)."""
    system, truth, measurement = aberrated_case()
    volume, measurement = truth.double(), measurement.double()
    jpgm = JPGM(system, DEPTHS, dtype=torch.float64)
    with torch.no_grad():
        jpgm.zernike_coefficients[:3] = torch.tensor([0.05, -0.02, 0.03])
    for parameter in jpgm.parameters():
        parameter.requires_grad_(True)

    def operator(psf):
        return MeasuredOperator(psf, measurement.shape[1:], 0, GAINS)

    def small_device(psf):
        if psf.requires_grad and psf.shape[1] > 2:
            raise torch.OutOfMemoryError("CUDA out of memory (a device for 2 depths)")
        return operator(psf)

    def update(model, chunks):
        jpgm.zero_grad(set_to_none=True)
        loss = fitted_update(jpgm, model, volume, measurement, 1, None, chunks)
        return loss, [parameter.grad.clone() for parameter in jpgm.parameters()]

    whole_loss, whole = update(operator, DepthChunks(0, len(DEPTHS), "cpu"))
    chunks = DepthChunks("auto", len(DEPTHS), "cuda")
    assert chunks.size == 0
    with pytest.warns(RuntimeWarning, match="out of GPU memory") as caught:
        loss, chunked = update(small_device, chunks)
    assert [str(w.message).split("chunks of ")[1][:6] for w in caught] == ["4 of 7", "2 of 7"]
    assert chunks.size == 2
    assert float(loss) == pytest.approx(float(whole_loss), rel=1e-12)
    for expected, actual in zip(whole, chunked):
        assert expected.abs().max() > 0
        torch.testing.assert_close(actual, expected, rtol=1e-9, atol=1e-12)
    with pytest.raises(torch.OutOfMemoryError):
        update(small_device, DepthChunks(0, len(DEPTHS), "cuda"))
    on_cpu = DepthChunks("auto", 101, "cpu")
    assert on_cpu.size == CPU_DEPTH_CHUNK and not on_cpu.shrink()
    assert DepthChunks("auto", CPU_DEPTH_CHUNK, "cpu").size == 0
    assert OpticsEstimation(depth_chunk="auto").depth_chunk == "auto"


def test_blur_schedule_and_blurred_data_loss():
    """``blur_px``: event k (after steps start + (k + 1) every) blurs by ``blur_px[k]``, the last
    entry from then on. The event's data loss is the pixel loss of the masked views, each
    blurred as scipy's gaussian_filter does, and its depth-chunked gradient the whole stack's."""
    from scipy import ndimage

    schedule = OpticsEstimation(estimate="zernike", start=200, every=50, blur_px=(4, 2, 1, 0))
    assert [schedule.blur_at(step) for step in (250, 300, 350, 400, 1000)] == [4, 2, 1, 0, 0]
    assert OpticsEstimation(estimate="zernike").blur_at(250) == 0.0
    slow = OpticsEstimation(estimate="zernike", start=0, every=10, blur_px=(3, 0), blur_events=2)
    assert [slow.blur_at(step) for step in (10, 20, 30, 40, 90)] == [3, 3, 0, 0, 0]
    with pytest.raises(ValueError, match="optics.blur_events >= 1"):
        OpticsEstimation(blur_events=0)
    for bad in ((-1.0,), (float("inf"),), (True,), ("4",), 4.0):
        with pytest.raises(ValueError, match="optics.blur_px must be a list of finite blurs"):
            OpticsEstimation(blur_px=bad)
    with pytest.raises(ValueError, match="optics.blur_events must be a whole number"):
        OpticsEstimation(blur_events=2.5)

    system, truth, measurement = aberrated_case()
    volume, measurement = truth.double(), measurement.double()
    mask = torch.ones_like(measurement)
    mask[1, 3:10, 4:8] = 0
    jpgm = JPGM(system, DEPTHS, dtype=torch.float64)
    with torch.no_grad():
        jpgm.zernike_coefficients[:3] = torch.tensor([0.2, -0.1, 0.05])
    jpgm.zernike_coefficients.requires_grad_(True)

    def operator(psf):
        return MeasuredOperator(psf, measurement.shape[1:], 0, GAINS)

    def blurred(views):
        return np.stack(
            [ndimage.gaussian_filter(v, 2.0, mode="constant", truncate=3.5) for v in views]
        )

    with torch.no_grad():
        prediction = operator(jpgm()).forward(volume).numpy()
    m = mask.numpy()
    expected = np.abs(blurred(m * prediction) - blurred(m * measurement.numpy())).mean()
    gradients = []
    for chunk in (0, 3):
        jpgm.zero_grad(set_to_none=True)
        loss = data_loss_backward(jpgm, operator, volume, measurement, 1, mask, chunk, 2.0)
        assert float(loss) == pytest.approx(expected, rel=1e-12)
        gradients.append(jpgm.zernike_coefficients.grad.clone())
    assert gradients[0].abs().max() > 0
    torch.testing.assert_close(gradients[1], gradients[0], rtol=1e-9, atol=1e-12)
