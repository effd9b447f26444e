"""The image encoder: an IBRNet-style ResUNet trained from scratch (docs/method.md §1.1).

Shapes: N images (N = B·V when the model encodes every source view of every scene at once),
H×W image size, h×w = ceil(H/s)×ceil(W/s) feature-map size (output stride s = 4, or 2), D feature
width, C channels.

Layout (ResNet BasicBlocks, layer4 unused, no max-pool):

  input [N, H, W, 9] ── 7×7/2 conv → IN → ReLU ─────────────────────── [N, H/2, W/2, 64]
    layer1 (blocks[0] × BasicBlock, stride 2) ─────────── x1           [N, H/4, W/4, 64]
    layer2 (blocks[1] × BasicBlock, stride 2) ─────────── x2           [N, H/8, W/8, 128]
    layer3 (blocks[2] × BasicBlock, stride 2) ─────────── x3           [N, H/16, W/16, 256]
    up(x3) → 3×3 conv 256→128 → IN → ELU; [up, x2] → 3×3 conv → 128 → IN → ELU
    up(·)  → 3×3 conv 128→64  → IN → ELU; [up, x1] → 3×3 conv → D   → IN → ELU
   (output_stride 2 only: up(·) → 3×3 conv → D → IN → ELU; [up, stem] → 3×3 conv → D → IN → ELU)
    1×1 conv D → D ────────────────────────────────────── [N, H/s, W/s, D], s = output_stride

The paper's map is a quarter of the image (output_stride 4). output_stride 2 is an option of this
repository, not the paper's: one more decoder stage joins the stem's half-resolution output, so a
64 px CLEVR object, one or two cells of a 16×16 map, covers four times as many cells, for slot
attention and for the features lifted at its outline.

Every convolution pads by reflection (the official code's `padding_mode='reflect'`); the stem and the
residual-block convolutions have no bias, the decoder's convolutions and the final 1×1 do. IN is
InstanceNorm with affine parameters (GroupNorm with one channel per group, ε = 1e-5, as PyTorch).
"up" is bilinear resampling with align_corners=True semantics; for H, W divisible by 16 it is exactly
×2 as in the official code. For other sizes the official code upsamples ×2 and zero-pads the skip
tensor to match (e.g. 300×400 DTU images give a 76×100 map whose last row sees a zero skip); we
instead resample to the skip tensor's size, so the map is always ceil(H/s)×ceil(W/s) and its pixel
grid spans the image exactly as the lifting step (docs/method.md §1.3) assumes.

Weights use PyTorch's default convolution init (uniform ±1/√fan_in for kernel and bias), since the
official model does not override it.

`dtype` is the computation dtype of every convolution and of the InstanceNorm outputs (the model's
`model.dtype`, see model.py); parameters and the InstanceNorm statistics stay float32.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from slotlifter_jax import config_checks

# PyTorch's InstanceNorm2d default, kept so the normalisation matches the official model.
INSTANCE_NORM_EPS = 1e-5


def resize_bilinear_align_corners(x: jax.Array, *, height: int, width: int) -> jax.Array:
  """Bilinear resampling of [..., h, w, C] to [..., height, width, C], align_corners=True.

  Output pixel i samples input coordinate i·(h−1)/(height−1), so the corner pixels of input and
  output coincide (PyTorch `interpolate(..., mode='bilinear', align_corners=True)`).
  `jax.image.resize` uses half-pixel centres instead, which is a different map.
  """
  def axis_weights(n_in, n_out):
    # Source coordinate of every output index, then its two neighbours and the blend factor.
    if n_out == 1 or n_in == 1:
      coord = jnp.zeros((n_out,), jnp.float32)
    else:
      coord = jnp.arange(n_out, dtype=jnp.float32) * ((n_in - 1) / (n_out - 1))
    lo = jnp.clip(jnp.floor(coord).astype(jnp.int32), 0, n_in - 1)
    hi = jnp.minimum(lo + 1, n_in - 1)
    frac = coord - lo.astype(jnp.float32)
    return lo, hi, frac

  h_in, w_in = x.shape[-3], x.shape[-2]
  y_lo, y_hi, y_frac = axis_weights(h_in, height)
  x_lo, x_hi, x_frac = axis_weights(w_in, width)
  # Separable: rows first, then columns.
  top = jnp.take(x, y_lo, axis=-3)  # [..., height, w, C]
  bottom = jnp.take(x, y_hi, axis=-3)
  rows = top + (bottom - top) * y_frac[:, None, None].astype(x.dtype)
  left = jnp.take(rows, x_lo, axis=-2)  # [..., height, width, C]
  right = jnp.take(rows, x_hi, axis=-2)
  return left + (right - left) * x_frac[:, None].astype(x.dtype)


def torch_default_kernel_init():
  """PyTorch's default Conv/Linear kernel init: kaiming_uniform(a=√5) = uniform(±1/√fan_in)."""
  return nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def torch_default_bias_init(fan_in: int):
  """PyTorch's default Conv/Linear bias init: uniform(±1/√fan_in) of the layer's kernel fan-in."""
  bound = 1.0 / math.sqrt(fan_in)

  def init(key, shape, dtype=jnp.float32):
    return jax.random.uniform(key, shape, dtype, -bound, bound)
  return init


class ReflectConv(nn.Module):
  """k×k convolution with reflect padding of (k−1)//2 on each side, then a VALID convolution."""
  features: int
  kernel_size: int
  stride: int = 1
  use_bias: bool = True
  dtype: Any = jnp.float32  # computation dtype; the kernel and bias stay float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:  # [N, H, W, C]
    pad = (self.kernel_size - 1) // 2
    if pad:
      x = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="reflect")
    fan_in = self.kernel_size * self.kernel_size * x.shape[-1]
    return nn.Conv(
        self.features, (self.kernel_size, self.kernel_size), strides=self.stride,
        padding="VALID", use_bias=self.use_bias, kernel_init=torch_default_kernel_init(),
        bias_init=torch_default_bias_init(fan_in), dtype=self.dtype, name="conv")(x)


def instance_norm(name: str, dtype: Any = jnp.float32) -> nn.Module:
  """InstanceNorm with affine parameters: statistics over H×W per image and channel.

  flax computes the statistics and the normalisation in float32 whatever the input dtype
  (`force_float32_reductions`, its default) and returns them in `dtype`, which feeds the next
  convolution.
  """
  return nn.GroupNorm(num_groups=None, group_size=1, epsilon=INSTANCE_NORM_EPS,
                      use_fast_variance=False, dtype=dtype, name=name)


class BasicBlock(nn.Module):
  """ResNet BasicBlock: conv3×3/s → IN → ReLU → conv3×3 → IN, + (1×1/s conv → IN)(x), ReLU."""
  features: int
  stride: int = 1
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    conv = lambda k, stride, name: ReflectConv(self.features, k, stride, use_bias=False,
                                               dtype=self.dtype, name=name)
    y = conv(3, self.stride, "conv1")(x)
    y = nn.relu(instance_norm("norm1", self.dtype)(y))
    y = conv(3, 1, "conv2")(y)
    y = instance_norm("norm2", self.dtype)(y)
    identity = x
    if self.stride != 1 or x.shape[-1] != self.features:
      identity = conv(1, self.stride, "down_conv")(x)
      identity = instance_norm("down_norm", self.dtype)(identity)
    return nn.relu(y + identity)


class ConvNormElu(nn.Module):
  """The decoder's conv → IN → ELU unit (IBRNet `conv`), with bias."""
  features: int
  kernel_size: int = 3
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = ReflectConv(self.features, self.kernel_size, dtype=self.dtype, name="conv")(x)
    return nn.elu(instance_norm("norm", self.dtype)(x))


class ResUNet(nn.Module):
  """[N, H, W, C_in] → [N, ceil(H/s), ceil(W/s), out_dim], s = output_stride (module docstring)."""
  out_dim: int = 64
  stem_width: int = 64
  widths: Sequence[int] = (64, 128, 256)
  blocks: Sequence[int] = (3, 4, 6)
  output_stride: int = 4
  dtype: Any = jnp.float32  # computation dtype (see the module docstring); the output is in it

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    if len(self.widths) != 3 or len(self.blocks) != 3:
      raise ValueError(f"ResUNet needs three layers, got widths={self.widths} "
                       f"blocks={self.blocks}")
    config_checks.check_output_stride(self.output_stride)
    x = ReflectConv(self.stem_width, 7, 2, use_bias=False, dtype=self.dtype,
                    name="stem_conv")(x)
    x = nn.relu(instance_norm("stem_norm", self.dtype)(x))  # [N, H/2, W/2, stem]
    stem = x

    skips = []
    for layer, (width, count) in enumerate(zip(self.widths, self.blocks)):
      for i in range(count):
        x = BasicBlock(width, stride=2 if i == 0 else 1, dtype=self.dtype,
                       name=f"layer{layer + 1}_{i}")(x)
      skips.append(x)
    x1, x2, x3 = skips  # [N, H/4, W/4, w0], [N, H/8, W/8, w1], [N, H/16, W/16, w2]

    def up(y, skip):
      return resize_bilinear_align_corners(y, height=skip.shape[-3], width=skip.shape[-2])

    unit = lambda width, name: ConvNormElu(width, dtype=self.dtype, name=name)
    x = unit(self.widths[1], "upconv3")(up(x3, x2))
    x = unit(self.widths[1], "iconv3")(jnp.concatenate([x, x2], axis=-1))
    x = unit(self.widths[0], "upconv2")(up(x, x1))
    x = unit(self.out_dim, "iconv2")(jnp.concatenate([x, x1], axis=-1))
    if self.output_stride == 2:
      x = unit(self.out_dim, "upconv1")(up(x, stem))
      x = unit(self.out_dim, "iconv1")(jnp.concatenate([x, stem], axis=-1))
    return ReflectConv(self.out_dim, 1, dtype=self.dtype, name="out_conv")(x)  # [N, h, w, D]
