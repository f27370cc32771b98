"""PSNR / SSIM against known values, both flavours, and per-frame averaging."""

import pytest
import torch

from isodream_rl.video_prediction.metrics import (
    FrameMetrics,
    psnr_per_sample,
    ssim_per_sample,
    uint8_psnr_per_sample,
    uint8_ssim_per_sample,
)


def test_psnr_of_a_constant_offset_is_known():
    target = torch.full((2, 3, 16, 16), 0.5)
    pred = target + 0.1  # MSE 0.01 -> 20 dB
    torch.testing.assert_close(psnr_per_sample(pred, target), torch.full((2,), 20.0))


def test_ssim_of_identical_images_is_one():
    x = torch.rand(3, 3, 32, 32)
    torch.testing.assert_close(ssim_per_sample(x, x), torch.ones(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(uint8_ssim_per_sample(x, x), torch.ones(3), atol=1e-6, rtol=0)


def test_uint8_ssim_of_flat_images_matches_closed_form():
    # Zero variance: SSIM = (2ab + C1) / (a^2 + b^2 + C1), with a, b the truncated uint8 values.
    a, b = torch.full((1, 3, 16, 16), 100 / 255 + 1e-4), torch.full((1, 3, 16, 16), 60 / 255 + 1e-4)
    c1 = (0.01 * 255) ** 2
    expected = (2 * 100 * 60 + c1) / (100**2 + 60**2 + c1)
    torch.testing.assert_close(uint8_ssim_per_sample(a, b), torch.tensor([expected]))


def test_uint8_metrics_truncate_like_the_authors():
    target = torch.zeros(1, 3, 4, 4)
    pred = torch.full((1, 3, 4, 4), 0.999 / 255)  # truncates to 0: a perfect uint8 match
    assert torch.isinf(uint8_psnr_per_sample(pred, target)).all()
    pred = torch.full((1, 3, 4, 4), 1.5 / 255)  # truncates to 1: MSE 1 -> 20 log10 255
    torch.testing.assert_close(
        uint8_psnr_per_sample(pred, target), torch.tensor([48.1308]), atol=1e-3, rtol=0
    )


def test_frame_metrics_average_samples_per_frame_then_frames():
    metrics = FrameMetrics()
    target = torch.full((2, 2, 3, 16, 16), 0.5)
    pred = target.clone()
    pred[:, 0] += 0.1  # frame 0: 20 dB
    pred[0, 1] += 0.01  # frame 1: 40 dB for sample 0 ...
    pred[1, 1] += 0.001  # ... and 60 dB for sample 1
    metrics.update(pred[:1], target[:1])
    metrics.update(pred[1:], target[1:])
    curves = metrics.compute()
    torch.testing.assert_close(curves["psnr"], torch.tensor([20.0, 50.0]), atol=1e-3, rtol=0)
    summary = FrameMetrics.summarize(curves, (1, 2))
    assert summary["psnr_1"] == pytest.approx(20.0, abs=1e-3)
    assert summary["psnr_2"] == pytest.approx(35.0, abs=1e-3)
    with pytest.raises(ValueError, match="horizon"):
        FrameMetrics.summarize(curves, (3,))


def test_mismatched_shapes_are_rejected():
    with pytest.raises(ValueError, match="shape"):
        psnr_per_sample(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(ValueError, match="before any update"):
        FrameMetrics().compute()
