"""Image metrics: SSIM against scikit-image, PSNR, crops, IoU, and LPIPS weight handling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cogs.eval import lpips as lp
from cogs.eval.metrics import (
    LPIPSAlex,
    crop_to_mask,
    image_metrics,
    iou,
    lpips_alex,
    lpips_status,
    mask_bbox,
    psnr,
    ssim,
    ssim_torch,
)
from cogs.ssim import ssim as loss_ssim

skimage_metrics = pytest.importorskip("skimage.metrics")


def _sk_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        skimage_metrics.structural_similarity(
            a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1
        )
    )


def _structured(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.stack(
        [0.5 + 0.5 * np.sin(9 * xx + 3 * yy), (xx > 0.5).astype(float) * 0.8 + 0.1, np.clip(yy + 0.2 * xx, 0, 1)],
        axis=-1,
    )
    return np.clip(img + 0.02 * rng.standard_normal(img.shape), 0, 1)


# --------------------------------------------------------------------------------------
# SSIM


@pytest.mark.parametrize("shape", [(20, 13, 3), (11, 11, 3), (37, 64, 3), (96, 80, 3), (32, 32, 1)])
def test_ssim_matches_scikit_image_on_random_and_structured_images(shape):
    rng = np.random.default_rng(sum(shape))
    pairs = []
    a = rng.random(shape)
    pairs.append((a, np.clip(a + 0.1 * rng.standard_normal(shape), 0, 1)))  # random + noise
    pairs.append((rng.random(shape), rng.random(shape)))  # unrelated
    s = _structured(*shape[:2], rng)[..., : shape[2]]
    pairs.append((s, np.clip(0.8 * s + 0.1 + 0.03 * rng.standard_normal(shape), 0, 1)))  # contrast change
    pairs.append((s, np.roll(s, 2, axis=1)))  # shift
    for p, g in pairs:
        assert abs(ssim(p, g) - _sk_ssim(p, g)) <= 1e-4
        # float32 torch input goes through the same path
        p32, g32 = torch.tensor(p, dtype=torch.float32), torch.tensor(g, dtype=torch.float32)
        assert abs(ssim(p32, g32) - _sk_ssim(p, g)) <= 1e-4


def test_ssim_depends_on_spatial_layout_not_just_pixel_statistics():
    # A statistic of the flattened pixel arrays is unchanged when the same permutation is
    # applied to both images; windowed 2-D SSIM is not: noise on a smooth image hurts much
    # more than the same noise on a shuffled (locally high-variance) one.
    rng = np.random.default_rng(3)
    img = _structured(48, 48, rng)
    noisy = np.clip(img + 0.05 * rng.standard_normal(img.shape), 0, 1)
    perm = rng.permutation(48 * 48)
    shuffle = lambda x: x.reshape(-1, 3)[perm].reshape(48, 48, 3)  # noqa: E731
    assert ssim(shuffle(noisy), shuffle(img)) > ssim(noisy, img) + 0.1


def test_ssim_of_identical_images_is_one():
    img = np.random.default_rng(0).random((30, 40, 3))
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)


def test_ssim_torch_is_differentiable_and_matches_numerical_gradient():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(13, 14, 2, generator=g, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn(13, 14, 2, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: ssim_torch(p, gt), (pred,))


def test_ssim_torch_batched_layout_equals_per_image_values():
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2, 3, 20, 25, generator=g)
    b = torch.rand(2, 3, 20, 25, generator=g)
    batched = ssim_torch(a, b)
    assert batched.shape == (2,)
    for i in range(2):
        single = ssim_torch(a[i].permute(1, 2, 0), b[i].permute(1, 2, 0))
        assert float(batched[i]) == pytest.approx(float(single), abs=1e-6)


def test_d_ssim_loss_decreases_under_gradient_descent():
    g = torch.Generator().manual_seed(2)
    gt = torch.rand(24, 24, 3, generator=g)
    pred = torch.full_like(gt, 0.5).requires_grad_(True)
    opt = torch.optim.Adam([pred], lr=0.05)
    first = None
    for _ in range(30):
        loss = 1 - ssim_torch(pred, gt)
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(1 - ssim_torch(pred.detach(), gt)) < 0.5 * first


@pytest.mark.parametrize("shape", [(11, 11, 3), (13, 40, 3), (64, 48, 1), (37, 29, 7)])
def test_fused_ssim_matches_the_torch_reference_in_value_and_gradient(shape):
    g = torch.Generator().manual_seed(sum(shape))
    gt = torch.rand(*shape, generator=g)
    gt[: shape[0] // 2] = gt[: shape[0] // 2].mean()  # flat half: small variances, where SSIM is steepest
    pred = (gt + 0.1 * torch.randn(*shape, generator=g)).clamp(0, 1).requires_grad_(True)
    p64 = pred.detach().double().requires_grad_(True)  # the reference in float64: both float32 paths round
    ref = ssim_torch(p64, gt.double())
    (g_ref,) = torch.autograd.grad(ref, p64)
    fused = loss_ssim(pred, gt)
    assert fused.grad_fn is not None and "Fused" in type(fused.grad_fn).__name__  # the kernels, not the fallback
    (g_fused,) = torch.autograd.grad(3.0 * fused, pred)  # an upstream gradient other than 1
    assert float(fused.detach()) == pytest.approx(float(ref.detach()), abs=1e-5)
    assert float((g_fused.double() - 3.0 * g_ref).abs().max()) <= 1e-4 * 3.0 * float(g_ref.abs().max())


def test_fused_ssim_takes_crops_of_larger_images_and_its_loss_descends():
    g = torch.Generator().manual_seed(3)
    gt = torch.rand(40, 50, 3, generator=g)
    full = torch.full_like(gt, 0.5).requires_grad_(True)
    opt = torch.optim.Adam([full], lr=0.05)
    first = None
    for _ in range(30):
        loss = 1 - loss_ssim(full[5:35, 10:45], gt[5:35, 10:45])  # non-contiguous views, as the objectives' crops
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        assert torch.all(full.grad[:5] == 0) and torch.all(full.grad[:, :10] == 0)  # nothing outside the crop
        opt.step()
    assert float(1 - ssim_torch(full.detach()[5:35, 10:45], gt[5:35, 10:45])) < 0.5 * first


def test_ssim_falls_back_to_the_reference_where_the_fused_kernels_do_not_apply():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(20, 20, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(20, 20, 3, generator=g, dtype=torch.float64, requires_grad=True)
    value = loss_ssim(a, b)  # float64, and the second image needs a gradient too
    assert value.dtype == torch.float64
    ga, gb = torch.autograd.grad(value, (a, b))
    ra, rb = torch.autograd.grad(ssim_torch(a, b), (a, b))
    assert torch.equal(ga, ra) and torch.equal(gb, rb)


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))


# --------------------------------------------------------------------------------------
# PSNR


def test_psnr_matches_closed_form_for_constant_error():
    gt = np.full((8, 9, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)  # mse 0.01 -> 20 dB
    assert psnr(torch.tensor(gt + 0.01), torch.tensor(gt)) == pytest.approx(40.0, abs=1e-6)
    assert psnr(gt, gt) == math.inf


def test_psnr_with_mask_uses_only_masked_pixels():
    gt = np.zeros((10, 10, 3))
    pred = gt.copy()
    pred[:5] = 0.1  # error only in the top half
    mask = np.zeros((10, 10), bool)
    mask[5:] = True
    assert psnr(pred, gt, mask=mask) == math.inf
    mask[:5] = True
    mask[5:] = False
    assert psnr(pred, gt, mask=mask) == pytest.approx(20.0, abs=1e-9)
    with pytest.raises(ValueError, match="empty"):
        psnr(pred, gt, mask=np.zeros((10, 10), bool))


# --------------------------------------------------------------------------------------
# Crops and IoU


def test_mask_bbox_is_tight_and_end_exclusive():
    mask = np.zeros((20, 30), bool)
    mask[4:9, 10:17] = True
    mask[12, 3] = True
    assert mask_bbox(mask) == (4, 13, 3, 17)
    assert mask_bbox(torch.tensor(mask)[..., None].float()) == (4, 13, 3, 17)
    assert mask_bbox(np.zeros((5, 5), bool)) is None


def test_crop_to_mask_crops_render_and_ground_truth_alike_with_padding_clamped():
    pred = torch.arange(20 * 30 * 3, dtype=torch.float32).reshape(20, 30, 3)
    gt = pred + 1
    mask = torch.zeros(20, 30, dtype=torch.bool)
    mask[1:5, 25:28] = True
    p, g = crop_to_mask(pred, gt, mask)
    assert p.shape == g.shape == (4, 3, 3)
    assert torch.equal(p, pred[1:5, 25:28]) and torch.equal(g, gt[1:5, 25:28])
    p, g = crop_to_mask(pred, gt, mask, pad=3)
    assert torch.equal(p, pred[0:8, 22:30]) and torch.equal(g, gt[0:8, 22:30])
    assert crop_to_mask(pred, gt, torch.zeros(20, 30, dtype=torch.bool)) is None


def test_iou_values_and_empty_union_convention():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    a[:2] = True  # 8 px
    b[1:3] = True  # 8 px, 4 shared
    assert iou(a, b) == pytest.approx(4 / 12)
    assert iou(a, a) == 1.0
    assert iou(a, ~a) == 0.0
    empty = np.zeros((4, 4), bool)
    assert iou(empty, empty) == 1.0
    assert math.isnan(iou(empty, empty, empty=float("nan")))


# --------------------------------------------------------------------------------------
# LPIPS


@pytest.fixture
def no_lpips_weights(tmp_path, monkeypatch):
    """An environment where neither weight file can be found anywhere."""
    monkeypatch.delenv(lp.ENV_BACKBONE, raising=False)
    monkeypatch.delenv(lp.ENV_LINEAR, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None, raising=False)
    monkeypatch.setattr(lp, "_find_spec", lambda name: None)
    return tmp_path


def test_lpips_unavailable_returns_none_with_a_reason_naming_the_files(no_lpips_weights):
    img = np.random.default_rng(0).random((40, 40, 3))
    assert lpips_alex(img, img) is None
    reason = lpips_status()
    assert "alexnet-owt-7be5be79.pth" in reason
    assert str(no_lpips_weights / "torch_home") in reason
    assert lp.ENV_LINEAR in reason
    notes: list[str] = []
    out = image_metrics(img, img, notes=notes)
    assert out["lpips"] is None and out["psnr"] == math.inf and out["ssim"] == pytest.approx(1.0)
    assert any("lpips is null" in n for n in notes)


def test_lpips_env_var_pointing_nowhere_is_reported_not_skipped(no_lpips_weights, monkeypatch):
    monkeypatch.setenv(lp.ENV_BACKBONE, str(no_lpips_weights / "missing.pth"))
    assert lpips_alex(np.zeros((32, 32, 3)), np.zeros((32, 32, 3))) is None
    assert "missing.pth" in lpips_status() and lp.ENV_BACKBONE in lpips_status()


def _write_random_weights(tmp_path, seed: int = 0, layout: str = "torchvision"):
    """Random AlexNet weights in the torchvision layout and lin weights in the lpips layout."""
    g = torch.Generator().manual_seed(seed)
    ref = lp.AlexFeatures()
    backbone = {}
    for key, value in ref.state_dict().items():  # keys "features.{i}.weight|bias"
        backbone[key] = 0.05 * torch.randn(value.shape, generator=g)
    if layout == "torchvision":  # the real file also holds the classifier
        backbone["classifier.1.weight"] = torch.randn(8, 4, generator=g)
    elif layout == "lpips":  # lpips model layout: net.slice{k}.{i}.weight
        slice_of = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
        backbone = {
            f"net.slice{slice_of[int(k.split('.')[1])]}.{k.split('.', 1)[1]}": v for k, v in backbone.items()
        }
    linear = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(lp.CHANNELS)}
    bpath, lpath = tmp_path / f"alexnet_{layout}_{seed}.pth", tmp_path / f"alex_{seed}.pth"
    torch.save(backbone, bpath)
    torch.save(linear, lpath)
    return bpath, lpath


def test_lpips_loads_local_weight_files_and_behaves_like_a_distance(no_lpips_weights, monkeypatch):
    bpath, lpath = _write_random_weights(no_lpips_weights)
    monkeypatch.setenv(lp.ENV_BACKBONE, str(bpath))
    monkeypatch.setenv(lp.ENV_LINEAR, str(lpath))
    assert "available" in lpips_status()
    rng = np.random.default_rng(1)
    gt = _structured(64, 64, rng)
    small = np.clip(gt + 0.05 * rng.standard_normal(gt.shape), 0, 1)
    large = np.clip(gt + 0.3 * rng.standard_normal(gt.shape), 0, 1)
    d_same = lpips_alex(gt, gt)
    d_small = lpips_alex(small, gt)
    d_large = lpips_alex(large, gt)
    assert d_same == pytest.approx(0.0, abs=1e-7)
    assert all(math.isfinite(d) for d in (d_small, d_large))
    assert 0 < d_small < d_large
    assert lpips_alex(gt, small) == pytest.approx(d_small, rel=1e-5)
    assert image_metrics(small, gt)["lpips"] == pytest.approx(d_small, rel=1e-5)


def test_lpips_finds_the_torch_hub_cache_and_an_installed_lpips_package(no_lpips_weights, monkeypatch):
    bpath, lpath = _write_random_weights(no_lpips_weights, seed=1)
    hub = no_lpips_weights / "torch_home" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / lp.ALEXNET_CHECKPOINT).write_bytes(bpath.read_bytes())
    pkg = no_lpips_weights / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "weights" / "v0.1" / "alex.pth").write_bytes(lpath.read_bytes())

    class Spec:
        submodule_search_locations = [str(pkg)]

    monkeypatch.setattr(lp, "_find_spec", lambda name: Spec() if name == "lpips" else None)
    img = np.random.default_rng(2).random((48, 40, 3))
    value = lpips_alex(img, img * 0.5)
    assert value is not None and value > 0
    assert str(hub / lp.ALEXNET_CHECKPOINT) in lpips_status()


def test_lpips_accepts_the_lpips_model_layout_and_gives_the_same_value(no_lpips_weights):
    tv_b, lin = _write_random_weights(no_lpips_weights, seed=3, layout="torchvision")
    lp_b, _ = _write_random_weights(no_lpips_weights, seed=3, layout="lpips")
    rng = np.random.default_rng(3)
    a, b = rng.random((40, 50, 3)), rng.random((40, 50, 3))
    v1 = lpips_alex(a, b, backbone_path=tv_b, linear_path=lin)
    v2 = lpips_alex(a, b, backbone_path=lp_b, linear_path=lin)
    assert v1 is not None and v1 == pytest.approx(v2, rel=1e-6)


def test_lpips_corrupt_weight_file_degrades_to_none(no_lpips_weights):
    bad = no_lpips_weights / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    _, lin = _write_random_weights(no_lpips_weights, seed=4)
    img = np.zeros((40, 40, 3))
    assert lpips_alex(img, img, backbone_path=bad, linear_path=lin) is None
    assert "could not be loaded" in lpips_status(backbone_path=bad, linear_path=lin)


def test_lpips_module_is_differentiable_for_use_as_a_loss():
    torch.manual_seed(0)
    model = LPIPSAlex()
    for prm in model.parameters():
        prm.data.normal_(0, 0.05)
    gt = torch.rand(1, 3, 40, 40)
    pred = torch.rand(1, 3, 40, 40, requires_grad=True)
    model(pred, gt).sum().backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_image_metrics_reports_null_with_notes_for_tiny_crops(no_lpips_weights, monkeypatch):
    bpath, lpath = _write_random_weights(no_lpips_weights, seed=5)
    monkeypatch.setenv(lp.ENV_BACKBONE, str(bpath))
    monkeypatch.setenv(lp.ENV_LINEAR, str(lpath))
    rng = np.random.default_rng(5)
    notes: list[str] = []
    out = image_metrics(rng.random((20, 13, 3)), rng.random((20, 13, 3)), notes=notes)
    assert out["ssim"] is not None and out["lpips"] is None and math.isfinite(out["psnr"])
    notes.clear()
    out = image_metrics(rng.random((8, 30, 3)), rng.random((8, 30, 3)), notes=notes)
    assert out["ssim"] is None and out["lpips"] is None
    assert len(notes) == 2


def test_unavailable_lpips_is_explained_once_not_per_section():
    from cogs.eval.evaluate import _summarise_notes

    reason = "lpips is null: AlexNet backbone weights not found: looked for X"
    notes = [reason, reason, "full.lpips: not computable (unavailable for every frame)",
             "test_time_pose_fit.human_crop.lpips: not computable (unavailable for every frame)",
             "lpips is null: image 9x9 is smaller than 16", "ssim is null: image 5x5 is smaller than 7"]
    out = _summarise_notes(notes)
    assert out.count(reason) == 1
    assert not any("not computable" in n for n in out)
    assert "lpips is null in every section (the reason above)" in out
    assert not any(n.startswith("lpips is null for") for n in out)  # no crop-size fold for it
    assert any(n.startswith("ssim is null for 1 crop(s)") for n in out)


def test_report_table_keeps_the_test_time_pose_fit_apart():
    from cogs.eval.report import metrics_table

    m = {"full": {"psnr": 30.0, "ssim": 0.9, "lpips": None},
         "test_time_pose_fit": {"steps": 40, "full": {"psnr": 31.0, "ssim": 0.95, "lpips": None},
                                "decomposition": {"human_iou": 0.86, "object_iou": None}}}
    rows = dict(metrics_table(m))
    assert rows["full"].startswith("psnr 30.00")
    assert rows["with test-time pose fit (40 steps): full"].startswith("psnr 31.00")
    assert "human_iou 0.8600" in rows["with test-time pose fit (40 steps): decomposition"]
