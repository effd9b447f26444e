"""Tests for the ResUNet image encoder (docs/method.md §1.1) against NumPy references."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import encoder


def _np_resize_align_corners(x, out_h, out_w):
  """Brute-force PyTorch bilinear interpolation, align_corners=True, one output pixel at a time."""
  n, h, w, c = x.shape
  out = np.zeros((n, out_h, out_w, c), np.float64)
  sy = (h - 1) / (out_h - 1) if out_h > 1 else 0.0
  sx = (w - 1) / (out_w - 1) if out_w > 1 else 0.0
  for i in range(out_h):
    for j in range(out_w):
      y, xx = i * sy, j * sx
      y0, x0 = int(np.floor(y)), int(np.floor(xx))
      y1, x1 = min(y0 + 1, h - 1), min(x0 + 1, w - 1)
      fy, fx = y - y0, xx - x0
      out[:, i, j] = ((1 - fy) * (1 - fx) * x[:, y0, x0] + (1 - fy) * fx * x[:, y0, x1]
                      + fy * (1 - fx) * x[:, y1, x0] + fy * fx * x[:, y1, x1])
  return out


@pytest.mark.parametrize("in_hw,out_hw", [((3, 5), (6, 10)), ((4, 7), (7, 13)), ((1, 3), (2, 6))])
def test_resize_align_corners_matches_numpy(in_hw, out_hw):
  x = np.random.default_rng(0).normal(size=(2,) + in_hw + (3,)).astype(np.float32)
  got = encoder.resize_bilinear_align_corners(jnp.asarray(x), height=out_hw[0], width=out_hw[1])
  chex.assert_shape(got, (2,) + out_hw + (3,))
  np.testing.assert_allclose(got, _np_resize_align_corners(x, *out_hw), atol=1e-5)


def test_resize_align_corners_is_not_half_pixel():
  # Corners coincide with align_corners=True; jax.image.resize (half-pixel) does not keep them.
  x = np.random.default_rng(1).normal(size=(1, 3, 5, 2)).astype(np.float32)
  got = np.asarray(encoder.resize_bilinear_align_corners(jnp.asarray(x), height=6, width=10))
  np.testing.assert_allclose(got[:, [0, -1]][:, :, [0, -1]], x[:, [0, -1]][:, :, [0, -1]],
                             atol=1e-6)
  half = np.asarray(jax.image.resize(jnp.asarray(x), (1, 6, 10, 2), "bilinear"))
  assert np.abs(half - got).max() > 1e-2


def test_instance_norm_matches_numpy():
  rng = np.random.default_rng(2)
  x = rng.normal(2.0, 3.0, size=(3, 5, 7, 11)).astype(np.float32)
  norm = encoder.instance_norm("norm")
  params = norm.init(jax.random.key(0), jnp.asarray(x))
  scale = rng.normal(size=11).astype(np.float32)
  bias = rng.normal(size=11).astype(np.float32)
  params = {"params": {"scale": jnp.asarray(scale), "bias": jnp.asarray(bias)}}
  got = norm.apply(params, jnp.asarray(x))
  xd = x.astype(np.float64)
  mean = xd.mean(axis=(1, 2), keepdims=True)
  var = xd.var(axis=(1, 2), keepdims=True)  # biased, as torch.nn.InstanceNorm2d
  want = (xd - mean) / np.sqrt(var + 1e-5) * scale + bias
  np.testing.assert_allclose(got, want, atol=1e-4)


def _np_reflect_conv(x, kernel, bias, stride):
  """Direct convolution (cross-correlation) of reflect-padded NHWC input, HWIO kernel."""
  k = kernel.shape[0]
  p = (k - 1) // 2
  xp = np.pad(x, ((0, 0), (p, p), (p, p), (0, 0)), mode="reflect")
  n, hp, wp, _ = xp.shape
  oh, ow = (hp - k) // stride + 1, (wp - k) // stride + 1
  out = np.zeros((n, oh, ow, kernel.shape[-1]))
  for i in range(oh):
    for j in range(ow):
      patch = xp[:, i * stride:i * stride + k, j * stride:j * stride + k, :]
      out[:, i, j] = np.einsum("nhwc,hwco->no", patch, kernel)
  return out + (0 if bias is None else bias)


@pytest.mark.parametrize("ksize,stride,use_bias", [(7, 2, False), (3, 1, True), (3, 2, False),
                                                   (1, 2, False)])
def test_reflect_conv_matches_numpy(ksize, stride, use_bias):
  x = np.random.default_rng(3).normal(size=(2, 9, 11, 5)).astype(np.float32)
  conv = encoder.ReflectConv(features=4, kernel_size=ksize, stride=stride, use_bias=use_bias)
  params = conv.init(jax.random.key(1), jnp.asarray(x))
  got = conv.apply(params, jnp.asarray(x))
  p = params["params"]["conv"]
  want = _np_reflect_conv(x.astype(np.float64), np.asarray(p["kernel"], np.float64),
                          np.asarray(p["bias"]) if use_bias else None, stride)
  assert ("bias" in p) == use_bias
  np.testing.assert_allclose(got, want, atol=1e-4)


def _tiny_unet():
  return encoder.ResUNet(out_dim=13, stem_width=8, widths=(8, 12, 16), blocks=(1, 2, 1))


def test_resunet_shapes_and_jit():
  x = jax.random.normal(jax.random.key(0), (2, 20, 28, 9))
  net = _tiny_unet()
  # An 'rbg' key: initialisation compiles much faster than with threefry on XLA:CPU.
  params = jax.jit(net.init)(jax.random.key(1, impl="rbg"), x)
  out = net.apply(params, x)
  chex.assert_shape(out, (2, 5, 7, 13))  # ceil(H/4) × ceil(W/4)
  np.testing.assert_allclose(jax.jit(net.apply)(params, x), out, atol=1e-5)
  # Images are encoded independently (instance norm, no batch statistics).
  np.testing.assert_allclose(net.apply(params, x[1:]), out[1:], atol=1e-5)


def test_output_stride_2_joins_the_stem_at_half_resolution():
  """The option: a ceil(H/2)×ceil(W/2) map from two more 3×3 stages (D → D on the upsampled map,
  then D + stem → D on it and the stem's output); the stride-4 layers keep their shapes."""
  x = jax.ShapeDtypeStruct((1, 20, 27, 9), jnp.float32)
  two = encoder.ResUNet(out_dim=13, stem_width=8, widths=(8, 12, 16), blocks=(1, 2, 1),
                        output_stride=2)
  p4 = jax.eval_shape(_tiny_unet().init, jax.random.key(0), x)["params"]
  p2 = jax.eval_shape(two.init, jax.random.key(0), x)["params"]
  assert jax.eval_shape(two.apply, {"params": p2}, x).shape == (1, 10, 14, 13)
  assert set(p2) - set(p4) == {"upconv1", "iconv1"} and not set(p4) - set(p2)
  shapes = lambda tree: jax.tree.map(lambda a: a.shape, tree)
  assert shapes({k: p2[k] for k in p4}) == shapes(p4)
  assert p2["upconv1"]["conv"]["conv"]["kernel"].shape == (3, 3, 13, 13)
  assert p2["iconv1"]["conv"]["conv"]["kernel"].shape == (3, 3, 13 + 8, 13)
  # The stem's output reaches the map: change the top-left 2×2 input pixels (one stem cell's
  # receptive field centre) and the map changes most near that corner.
  xs = np.random.default_rng(0).normal(size=(1, 32, 32, 9)).astype(np.float32)
  params = jax.jit(two.init)(jax.random.key(1, impl="rbg"), jnp.asarray(xs))
  bumped = xs.copy()
  bumped[0, :2, :2] += 3.0
  delta = np.abs(np.asarray(two.apply(params, bumped) - two.apply(params, xs))).sum(-1)[0]
  assert delta.shape == (16, 16) and delta[:2, :2].mean() > 2 * delta[8:, 8:].mean()
  with pytest.raises(ValueError, match=r"model.encoder_output_stride is 8; it must be one of"):
    jax.eval_shape(encoder.ResUNet(out_dim=4, output_stride=8).init, jax.random.key(0), x)


def test_resunet_default_layout():
  net = encoder.ResUNet(out_dim=64)
  x = jax.ShapeDtypeStruct((1, 128, 128, 9), jnp.float32)
  params = jax.eval_shape(net.init, jax.random.key(0), x)
  out = jax.eval_shape(net.apply, params, x)
  assert out.shape == (1, 32, 32, 64)
  p = params["params"]
  # Stem 7×7, no bias; three layers of (3, 4, 6) blocks; first block of each layer downsamples.
  assert p["stem_conv"]["conv"]["kernel"].shape == (7, 7, 9, 64)
  assert "bias" not in p["stem_conv"]["conv"]
  assert sorted(k for k in p if k.startswith("layer")) == sorted(
      [f"layer1_{i}" for i in range(3)] + [f"layer2_{i}" for i in range(4)]
      + [f"layer3_{i}" for i in range(6)])
  for layer in ("layer1_0", "layer2_0", "layer3_0"):
    assert "down_conv" in p[layer]
  assert "down_conv" not in p["layer2_1"]
  assert p["upconv3"]["conv"]["conv"]["kernel"].shape == (3, 3, 256, 128)
  assert p["iconv3"]["conv"]["conv"]["kernel"].shape == (3, 3, 256, 128)
  assert p["upconv2"]["conv"]["conv"]["kernel"].shape == (3, 3, 128, 64)
  assert p["iconv2"]["conv"]["conv"]["kernel"].shape == (3, 3, 128, 64)
  assert p["out_conv"]["conv"]["kernel"].shape == (1, 1, 64, 64)
