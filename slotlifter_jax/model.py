"""SlotLifter: encoder, slot attention, lifting and slot decoder composed (docs/method.md §1).

Shapes: B scenes, V source views, R rays per scene, S samples per ray (S + fine samples in the fine
pass), K slots (K+1 with the empty slot), D feature width, Ds slot width, C point width (64),
H×W source-image size, h×w feature-map size.

  encode:       source views → features [B, V, h, w, D] → slots [B, K, Ds]      (once per scene)
                (h×w = ceil(H/s)×ceil(W/s), s = model.encoder_output_stride, see encoder.py)
  render_rays:  rays → samples → lifted features F_lift + positional embedding E_p = F_p
                → allocation transformer + mapping (point-slot weights W, density σ)
                → colour MLP(F_s + E_p) → volume rendering; optionally a fine pass.

`render_rays` takes an `Encoded` so evaluation renders a full view in chunks of rays with the slots
computed once. The rng streams are 'params', 'dropout' (residual dropout, stochastic depth),
'noise' (slot initialisation), 'sample' (stratified jitter, fine samples) and 'mask' (random masking
of the lifted features); only 'params' is needed when `train` is False.

Choices where the method (docs/method.md) leaves room or the official code differs:
- Random masking keeps or drops a ray's lifted features alike in every scene of the batch
  (`mask_shared_across_batch=True`, as the official code), and the same per-ray mask applies to the
  fine pass (the official code never masks the fine pass, docs/method.md §8).
- Fine samples are random in training and deterministic at evaluation (the official code does the
  opposite, docs/method.md §8).
- The fine pass owns its lifting Linear as well as its allocation transformer, mapping and colour
  MLP, because in the official code all three live in the separate fine `NeRF`/`JointDecoder`;
  the encoder, slots and positional Linear are shared.
- Ablation switches of docs/method.md §5, each defaulting to the paper's method:
  `feature_lifting=False` ("without feature lifting") skips the projection and gather, so F_p = E_p
  and no lifting Linear exists (the encoder still feeds slot attention); `density_mode="mlp"`
  ("without slot-based density", decoder.SlotDecoder). "Without random masking" is
  `train.mask_max = 0` (keep ratio 1).
- Stratified samples use `geometry.stratified_depths`' default bins (all samples inside
  [near, far]); `volume_render` puts the transparent remainder at `far`.

Numerics (`model.dtype`, the `dtype` field): "float32" (the default) computes everything in
float32. "bfloat16" is mixed precision with float32 parameters: every Linear and convolution, and
the attention and point-slot products, multiply bfloat16 copies of their inputs and weights (half
the bytes, and twice the multiply rate on hardware with bf16 units), while what is sensitive to
rounding stays float32:
- the softmaxes (slot attention over slots, the decoder's attentions, W): the logits are cast to
  float32 after their product, so the exp, the sums over slots or keys and the division run in
  float32 (a bf16 sum of many terms drops the small ones); a weight enters its next product as a
  bf16 copy like any product input, while σ, the segmentation and slot attention's normalisation
  over all V·h·w inputs use the float32 weights;
- LayerNorm and InstanceNorm statistics and normalisation (flax computes them in float32 and
  returns the compute dtype for the next Linear);
- the positional encoding sin/cos(2^f·x) up to 2^9·x: in bf16 the argument 2^9·x of a point at
  |x| ≈ 2 would be a multiple of 8, more than the period 2π (only its Linear runs in bf16);
- the residual streams: the slots (the GRU state, which starts from the float32 μ) and the
  decoder's h, so rounding errors do not accumulate over blocks and iterations;
- the encoder's output features, the mapping logits A, W, σ and the colour (tanh of a float32
  cast), and with them all of volume rendering (transmittance, weights, composites), the
  geometry (rays, projection, sample points) and the loss (train_step.py).
Parameters, their gradients and the optimiser state are float32 in both modes (same shapes and
dtypes), so the check of a run's saved config (checkpoints.check_compatible) lets model.dtype
differ: a float32 run can be evaluated or resumed in bfloat16. tests/test_bf16.py states the
tolerances against the float32 model. On a CPU without AMX, such as the 2-core development machine
(AVX-512 BF16 only), bf16 is slower than float32 (×1.09 per step on bench config A, ×1.23 on B:
`experiments/bench.py --configs=A,B --dtypes=float32,bfloat16`, docs/performance.md §2), so
float32 stays the default.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import ml_collections

from slotlifter_jax import config_checks
from slotlifter_jax import decoder as decoder_lib
from slotlifter_jax import geometry
from slotlifter_jax import lifting
from slotlifter_jax.encoder import ResUNet
from slotlifter_jax.rendering import volume
from slotlifter_jax.slot_attention import SlotAttention

# Top-level submodules whose parameters follow the "head" learning-rate schedule (docs/method.md §2:
# colour MLP, lifting Linear, positional Linear); everything else is "backbone". Prefixes, so the
# fine pass's `colour_mlp_fine` and `lift_proj_fine` are included.
HEAD_MODULE_PREFIXES = ("colour_mlp", "lift_proj", "pos_proj")
# Slot attention's submodules (its input embedding included): a third schedule when
# train.slot_attention_lr_scale ≠ 1 (schedules.has_slot_attention_group).
SLOT_ATTENTION_MODULE_PREFIXES = ("slot_attention", "slot_pos_proj")

# `model.dtype` values → the computation dtype (module docstring, "Numerics").
COMPUTE_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


def compute_dtype(name: str):
  """The jnp dtype of a `model.dtype` name; ValueError for anything else."""
  if name not in COMPUTE_DTYPES:
    raise ValueError(f"model.dtype must be one of {sorted(COMPUTE_DTYPES)}, got {name!r}")
  return COMPUTE_DTYPES[name]


@flax.struct.dataclass
class Encoded:
  features: jax.Array  # [B, V, h, w, D] encoder feature maps
  slots: jax.Array  # [B, K, Ds]
  slot_attn: jax.Array  # [B, K, V·h·w] last slot-attention iteration, softmax over slots


@flax.struct.dataclass
class RenderOutput:
  coarse: volume.RenderResult  # colour [B, R, 3], depth [B, R], segmentation [B, R, K], …
  fine: Optional[volume.RenderResult]  # None without a fine pass
  # Of the last pass (the fine one when present, so S is then num_samples + num_fine_samples):
  point_slot_weights: jax.Array  # [B, R, S, K+1], index 0 = empty slot
  z: jax.Array  # [B, R, S] sample depths
  density: jax.Array  # [B, R, S] density σ (slot-based unless density_mode="mlp")
  # Per slot and per sample, for rendering each slot alone (rendering/pictures.py); unused outputs
  # of a jitted training step are dropped by the compiler, so they cost nothing there.
  slot_density: jax.Array  # [B, R, S, K] each real slot's share of σ; Σ_k = density
  sample_colour: jax.Array  # [B, R, S, 3] the colour MLP's output per sample


@flax.struct.dataclass
class ModelOutput:
  render: RenderOutput
  encoded: Encoded


def encoder_input(*, images: jax.Array, cam_to_world: jax.Array,
                  intrinsics: jax.Array) -> jax.Array:
  """The encoder's 9 input channels per pixel: RGB ⊕ camera origin ⊕ unit ray direction (§1.1).

  images [..., H, W, 3], cam_to_world [..., 4, 4], intrinsics [..., 3, 3] → [..., H, W, 9].
  """
  height, width = images.shape[-3], images.shape[-2]
  rays = geometry.pixel_rays(cam_to_world=cam_to_world[..., None, None, :, :],
                             intrinsics=intrinsics[..., None, None, :, :],
                             pix=geometry.image_pixels(height, width))  # [..., H, W, 3] each
  return jnp.concatenate([images, rays.origins.astype(images.dtype),
                          rays.directions.astype(images.dtype)], axis=-1)


def pooled_encoder_input(x: jax.Array, pool: int) -> jax.Array:
  """The encoder input of a view box-filtered by `pool`: [..., H, W, 9] → [..., H/p, W/p, 9].

  RGB and camera origin are the mean over each p×p block; the ray direction is the block's mean
  unit direction renormalised, the ray through the block's centre up to O((p·pixel/focal)²). The
  feature map of a pooled view keeps `lifting`'s align-corners mapping to full-size pixels, the
  same approximation a stride-s map already makes. Why: the encoder's cost grows with the pixel
  count, and a finer view may help the targets and the lifted colours more than slot attention.
  """
  config_checks.check_input_pool(pool)
  if pool == 1:
    return x
  height, width = x.shape[-3], x.shape[-2]
  if height % pool or width % pool:
    raise ValueError(f"model.encoder_input_pool is {pool}; the source views' {height}×{width} "
                     f"pixels must divide by it")
  blocks = x.reshape(x.shape[:-3] + (height // pool, pool, width // pool, pool, x.shape[-1]))
  mean = blocks.mean(axis=(-4, -2))  # [..., H/p, W/p, 9]
  directions = mean[..., 6:9] / jnp.linalg.norm(mean[..., 6:9], axis=-1, keepdims=True)
  return jnp.concatenate([mean[..., :6], directions], axis=-1)


def point_embedding_input(*, points: jax.Array, directions: jax.Array,
                          num_freqs: int) -> jax.Array:
  """[PE(xyz), PE(unit ray direction)] per sample (docs/method.md §1.3): points [B, R, S, 3],
  directions [B, R, 3] → [B, R, S, 12·num_freqs] (120 for 10 frequencies)."""
  pe_points = geometry.positional_encoding(points, num_freqs)  # [B, R, S, 6F]
  pe_dirs = geometry.positional_encoding(directions, num_freqs)[..., None, :]  # [B, R, 1, 6F]
  pe_dirs = jnp.broadcast_to(pe_dirs, pe_points.shape)
  return jnp.concatenate([pe_points, pe_dirs], axis=-1)  # [B, R, S, 12F]


class PointEmbedding(nn.Module):
  """E_p = Linear([PE(xyz), PE(unit ray direction)]) per sample (docs/method.md §1.3).

  points [B, R, S, 3], directions [B, R, 3] → [B, R, S, C] float32. The Linear's parameters are
  those of one `nn.Dense` on the 12·num_freqs-wide concatenation (kernel rows: the points' 6F
  first), but the direction half is applied once per ray and broadcast over its S samples: the
  same function without S copies of the direction's sines, cosines and product.
  """
  features: int
  num_freqs: int = 10
  dtype: Any = jnp.float32  # computation dtype of the Linear; the encoding itself is float32

  @nn.compact
  def __call__(self, points: jax.Array, directions: jax.Array) -> jax.Array:
    width = 6 * self.num_freqs  # sin and cos of F frequencies of 3 coordinates
    kernel = self.param("kernel", nn.initializers.xavier_uniform(),
                        (2 * width, self.features), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
    kernel, bias = kernel.astype(self.dtype), bias.astype(self.dtype)
    # float32 encodings: in bfloat16 the argument 2^9·x would be coarser than the period 2π.
    pe_points = geometry.positional_encoding(points, self.num_freqs)  # [B, R, S, 6F]
    pe_dirs = geometry.positional_encoding(directions, self.num_freqs)  # [B, R, 6F]
    per_ray = pe_dirs.astype(self.dtype) @ kernel[width:] + bias  # [B, R, C]
    e_p = pe_points.astype(self.dtype) @ kernel[:width] + per_ray[..., None, :]
    return e_p.astype(jnp.float32)


class SlotLifter(nn.Module):
  """The whole model; build it from a config with `build_model`."""
  # Encoder (§1.1).
  feature_dim: int = 64
  encoder_stem_width: int = 64
  encoder_output_stride: int = 4  # 4: the paper's quarter-size feature map; 2: encoder.py
  # p: the encoder (and so slot attention) sees the source views box-filtered to H/p × W/p, while
  # lifting gathers RGB at full size and the targets stay full size (`pooled_encoder_input`).
  encoder_input_pool: int = 1
  encoder_widths: Sequence[int] = (64, 128, 256)
  encoder_blocks: Sequence[int] = (3, 4, 6)
  # Slot attention (§1.2).
  num_slots: int = 8
  slot_dim: int = 256
  slot_iters: int = 3
  slot_mlp_dim: int = 1024
  slot_eps: float = 1.0
  slot_drop_path: float = 0.2
  # Point decoder (§1.3, §1.4).
  point_dim: int = 64
  num_blocks: int = 4
  num_heads: int = 4
  self_attn_dim: int = 16
  ffn_dim: int = 256
  max_dropout: float = 0.2
  num_freqs: int = 10
  colour_hidden: int = 64
  colour_layers: int = 4
  colour_range: str = "unit"
  locality_box: float = 0.64
  remat_scan: bool = False
  # The decoder's cross-attention and mapping, and E_p's direction half, computed in a folded
  # order: the same parameters and function, fewer per-point products, other rounding
  # (decoder.py's module docstring, `PointEmbedding`).
  fold_products: bool = False
  mask_shared_across_batch: bool = True
  # Ablations (docs/method.md §5); the defaults are the paper's method.
  feature_lifting: bool = True  # False: F_p = E_p only
  density_mode: str = "slot"  # "slot" | "mlp" (decoder.SlotDecoder)
  # Rendering (§1.5).
  density_scale: float = 25.0
  density_log_init: float = 0.0
  near: float = 6.0 / 7.0
  far: float = 20.0 / 7.0
  num_samples: int = 96
  num_fine_samples: int = 0
  # () or (z_min, z_max): sample each ray only where it crosses this horizontal slab of the
  # normalised scene frame (`geometry.slab_interval`), e.g. from just below the floor to above the
  # tallest object; () samples all of [near, far] (the paper's).
  z_bounds: tuple = ()
  # Computation dtype of the Linear layers and convolutions (`compute_dtype`, module docstring
  # "Numerics"); parameters are float32 whatever it is.
  dtype: Any = jnp.float32

  def setup(self):
    self.encoder = ResUNet(out_dim=self.feature_dim, stem_width=self.encoder_stem_width,
                           widths=tuple(self.encoder_widths), blocks=tuple(self.encoder_blocks),
                           output_stride=self.encoder_output_stride, dtype=self.dtype)
    self.slot_attention = SlotAttention(
        num_slots=self.num_slots, slot_dim=self.slot_dim, num_iters=self.slot_iters,
        mlp_dim=self.slot_mlp_dim, eps=self.slot_eps, drop_path_rate=self.slot_drop_path,
        dtype=self.dtype)
    # xavier-uniform kernels, zero biases: the official `linear` helper.
    dense = lambda name: nn.Dense(self.point_dim, kernel_init=nn.initializers.xavier_uniform(),
                                  dtype=self.dtype, name=name)
    # E_p, shared by both passes; the folded form applies the direction half once per ray.
    self.pos_proj = (PointEmbedding(self.point_dim, self.num_freqs, dtype=self.dtype,
                                    name="pos_proj")
                     if self.fold_products else dense("pos_proj"))
    passes = ["", "_fine"] if self.num_fine_samples > 0 else [""]
    # One (lifting Linear, slot decoder, colour MLP) triple per pass; the input width of the lifting
    # Linear (D+3 for V = 1, 2(D+3) for V > 1) is inferred from the first call.
    self.lift_projs = [dense(f"lift_proj{p}") for p in passes]
    self.allocations = [
        decoder_lib.SlotDecoder(
            width=self.point_dim, num_blocks=self.num_blocks, num_heads=self.num_heads,
            self_attn_dim=self.self_attn_dim, ffn_dim=self.ffn_dim, max_dropout=self.max_dropout,
            remat_scan=self.remat_scan, locality_box=self.locality_box,
            density_log_init=self.density_log_init, density_mode=self.density_mode,
            fold_products=self.fold_products, dtype=self.dtype, name=f"allocation{p}")
        for p in passes]
    self.colour_mlps = [
        decoder_lib.ColourMLP(hidden=self.colour_hidden, num_layers=self.colour_layers,
                              colour_range=self.colour_range, dtype=self.dtype,
                              name=f"colour_mlp{p}")
        for p in passes]

  def encode(self, *, source_images: jax.Array, source_cam_to_world: jax.Array,
             source_intrinsics: jax.Array, slot_noise_sigma=0.0, train: bool) -> Encoded:
    """Source views [B, V, H, W, 3] (as given: the caller maps DTU images to [−1, 1]) → slots.

    slot_noise_sigma: the (traced) σ of the slot initialisation noise; only used when `train`.
    """
    b, v, height, width, _ = source_images.shape
    x = encoder_input(images=source_images, cam_to_world=source_cam_to_world,
                      intrinsics=source_intrinsics)  # [B, V, H, W, 9]
    x = pooled_encoder_input(x, self.encoder_input_pool)  # [B, V, H/p, W/p, 9]
    height, width = x.shape[2], x.shape[3]
    # float32 out of the encoder: lifting samples these maps bilinearly, slot attention normalises.
    feats = self.encoder(x.reshape((b * v, height, width, x.shape[-1]))).astype(
        jnp.float32)  # [B·V, h, w, D]
    feats = feats.reshape((b, v) + feats.shape[1:])  # [B, V, h, w, D]
    flat = feats.reshape(b, -1, feats.shape[-1])  # [B, V·h·w, D]: all views (§1.2)
    result = self.slot_attention(flat, noise_sigma=slot_noise_sigma, train=train)
    return Encoded(features=feats, slots=result.slots, slot_attn=result.attn)

  def _render_pass(self, index: int, encoded: Encoded, *, source_images, source_cam_to_world,
                   source_intrinsics, ray_origins, ray_directions, z, keep, locality, train,
                   last_delta=None):
    """One pass (0 coarse, 1 fine) at depths z [B, R, S] → (RenderResult, decoder Allocation).

    last_delta: None, or [B, R] the δ of the last sample when z is a window of a longer grid
    (`render_at_depths`)."""
    points = geometry.points_along_rays(origins=ray_origins, directions=ray_directions,
                                        z=z)  # [B, R, S, 3]
    f_lift = None  # "without feature lifting" (docs/method.md §5): views reach points via slots
    if self.feature_lifting:
      lifted = lifting.project_and_gather(
          points=points, cam_to_world=source_cam_to_world, intrinsics=source_intrinsics,
          images=source_images, features=encoded.features)  # values [B, R, S, V, D+3]
      fused = lifting.fuse_views(values=lifted.values, valid=lifted.valid)  # [B, R, S, (2)(D+3)]
      # float32: F_p starts the decoder's float32 residual stream.
      f_lift = self.lift_projs[index](fused).astype(jnp.float32)  # [B, R, S, C]
      if lifted.valid.shape[-1] == 1:
        # V = 1: valid·Linear(x), so an invalid point gets no bias either (official); the view
        # axis of valid [B, R, S, 1] broadcasts over C.
        f_lift = f_lift * lifted.valid
      if keep is not None:
        f_lift = lifting.apply_ray_mask(lifted=f_lift, keep=keep)
    # The encoding is float32 (geometry.positional_encoding of float32 points); only the Linear
    # runs in the computation dtype.
    if self.fold_products:
      e_p = self.pos_proj(points, ray_directions)  # [B, R, S, C] float32
    else:
      e_p = self.pos_proj(point_embedding_input(points=points, directions=ray_directions,
                                                num_freqs=self.num_freqs)).astype(
                                                    jnp.float32)  # [B, R, S, C]
    point_features = e_p if f_lift is None else f_lift + e_p  # F_p [B, R, S, C]
    alloc = self.allocations[index](point_features, encoded.slots, points, locality=locality,
                                    train=train)
    colour = self.colour_mlps[index](alloc.features + e_p)  # [B, R, S, 3]
    result = volume.volume_render(density=alloc.density, z=z, colour=colour,
                                  slot_weights=alloc.weights, far=self.far,
                                  density_scale=self.density_scale, last_delta=last_delta)
    return result, alloc, colour

  def ray_interval(self, ray_origins: jax.Array, ray_directions: jax.Array):
    """[near, far] of every ray: the config's scalars, or their part inside `z_bounds`."""
    if not self.z_bounds:
      return self.near, self.far
    z_min, z_max = (float(x) for x in self.z_bounds)
    return geometry.slab_interval(origins=ray_origins, directions=ray_directions, near=self.near,
                                  far=self.far, z_min=z_min, z_max=z_max)

  def render_rays(self, encoded: Encoded, *, source_images: jax.Array,
                  source_cam_to_world: jax.Array, source_intrinsics: jax.Array,
                  ray_origins: jax.Array, ray_directions: jax.Array, keep_ratio=1.0,
                  locality=False, train: bool, drop_lifted: bool = False) -> RenderOutput:
    """Renders rays [B, R, 3] (unit directions) of the scenes in `encoded`.

    keep_ratio: (traced) probability that a ray keeps its lifted features; used only when `train`.
    locality: (traced) bool switching the locality constraint (docs/method.md §1.4).
    drop_lifted: (static) render every ray as training renders a masked one (§1.3), its lifted
      features zeroed, so a point sees the views only through the slots and its own position: a
      diagnostic of what the slots alone carry. Evaluation keeps them.
    """
    b, r = ray_origins.shape[:2]
    sources = dict(source_images=source_images, source_cam_to_world=source_cam_to_world,
                   source_intrinsics=source_intrinsics)
    rays = dict(ray_origins=ray_origins, ray_directions=ray_directions)
    near, far = self.ray_interval(ray_origins, ray_directions)  # scalars or [B, R]
    z = geometry.stratified_depths(near=near, far=far, num_samples=self.num_samples,
                                   batch_shape=(b, r),
                                   key=self.make_rng("sample") if train else None)  # [B, R, S]
    if drop_lifted:
      keep = jnp.zeros((b, r), jnp.float32)  # every ray masked
    elif train:
      keep = lifting.sample_ray_keep(key=self.make_rng("mask"), keep_ratio=keep_ratio,
                                     shape=(b, r),
                                     shared_across_batch=self.mask_shared_across_batch)  # [B, R]
    else:
      keep = None
    coarse, alloc, colour = self._render_pass(0, encoded, **sources, **rays, z=z, keep=keep,
                                              locality=locality, train=train)
    fine = None
    if self.num_fine_samples > 0:
      # Importance samples from the detached coarse weights, merged with the coarse depths.
      z = geometry.fine_depths(z=z, weights=coarse.weights, num_samples=self.num_fine_samples,
                               key=self.make_rng("sample") if train else None)
      fine, alloc, colour = self._render_pass(1, encoded, **sources, **rays, z=z, keep=keep,
                                              locality=locality, train=train)
    return RenderOutput(coarse=coarse, fine=fine, point_slot_weights=alloc.weights, z=z,
                        density=alloc.density, slot_density=alloc.slot_densities,
                        sample_colour=colour)

  def render_at_depths(self, encoded: Encoded, *, source_images: jax.Array,
                       source_cam_to_world: jax.Array, source_intrinsics: jax.Array,
                       ray_origins: jax.Array, ray_directions: jax.Array, z: jax.Array,
                       last_delta: Optional[jax.Array] = None, locality=False) -> RenderOutput:
    """The coarse pass at evaluation at given depths z [B, R, S'] (adaptive rendering).

    With z = the evaluation grid and last_delta None this is `render_rays(train=False)`. The
    adaptive renderer (slotlifter_jax.rendering.adaptive) gives a window of that grid, S' ≤ S
    samples, and last_delta [B, R], the grid δ of the window's last sample. Models with a fine
    pass (DTU, ScanNet) are refused: their fine depths come from the coarse weights of the whole
    ray, which a window does not have (out of scope for adaptive rendering).
    """
    if self.num_fine_samples > 0:
      raise ValueError(f"render_at_depths: the model has a fine pass (num_fine_samples="
                       f"{self.num_fine_samples}); adaptive rendering covers coarse-only models "
                       f"(the synthetic sets) only, render with render.adaptive=False")
    coarse, alloc, colour = self._render_pass(
        0, encoded, source_images=source_images, source_cam_to_world=source_cam_to_world,
        source_intrinsics=source_intrinsics, ray_origins=ray_origins,
        ray_directions=ray_directions, z=z, keep=None, locality=locality, train=False,
        last_delta=last_delta)
    return RenderOutput(coarse=coarse, fine=None, point_slot_weights=alloc.weights, z=z,
                        density=alloc.density, slot_density=alloc.slot_densities,
                        sample_colour=colour)

  def __call__(self, *, source_images: jax.Array, source_cam_to_world: jax.Array,
               source_intrinsics: jax.Array, ray_origins: jax.Array, ray_directions: jax.Array,
               slot_noise_sigma=0.0, keep_ratio=1.0, locality=False,
               train: bool) -> ModelOutput:
    """encode + render_rays on the same scenes (the training forward pass)."""
    sources = dict(source_images=source_images, source_cam_to_world=source_cam_to_world,
                   source_intrinsics=source_intrinsics)
    encoded = self.encode(**sources, slot_noise_sigma=slot_noise_sigma, train=train)
    out = self.render_rays(encoded, **sources, ray_origins=ray_origins,
                           ray_directions=ray_directions, keep_ratio=keep_ratio,
                           locality=locality, train=train)
    return ModelOutput(render=out, encoded=encoded)


def build_model(config: ml_collections.ConfigDict) -> SlotLifter:
  """A SlotLifter from `config.model` and `config.render` (plain Python values, no ConfigDict)."""
  m, r = config.model, config.render
  return SlotLifter(
      feature_dim=int(m.feature_dim),
      encoder_stem_width=int(m.encoder_stem_width),
      encoder_widths=tuple(int(x) for x in m.encoder_widths),
      encoder_blocks=tuple(int(x) for x in m.encoder_blocks),
      encoder_output_stride=int(m.get("encoder_output_stride", 4)),
      encoder_input_pool=int(m.get("encoder_input_pool", 1)),
      num_slots=int(m.num_slots),
      slot_dim=int(m.slot_dim),
      slot_iters=int(m.slot_iters),
      slot_mlp_dim=int(m.slot_mlp_dim),
      slot_eps=float(m.slot_eps),
      slot_drop_path=float(m.slot_drop_path),
      point_dim=int(m.point_dim),
      num_blocks=int(m.num_blocks),
      num_heads=int(m.num_heads),
      self_attn_dim=int(m.self_attn_dim),
      ffn_dim=int(m.ffn_dim),
      max_dropout=float(m.max_dropout),
      num_freqs=int(m.num_freqs),
      colour_hidden=int(m.colour_hidden),
      colour_layers=int(m.colour_layers),
      colour_range=str(m.colour_range),
      locality_box=float(m.locality_box),
      remat_scan=bool(m.remat_scan),
      fold_products=bool(m.get("fold_products", False)),
      density_scale=float(m.density_scale),
      density_log_init=float(m.density_log_init),
      near=float(r.near),
      far=float(r.far),
      num_samples=int(r.num_samples),
      num_fine_samples=int(r.num_fine_samples),
      z_bounds=tuple(float(x) for x in r.get("z_bounds", ())),
      feature_lifting=bool(m.feature_lifting),
      density_mode=str(m.density_mode),
      dtype=compute_dtype(str(m.get("dtype", "float32"))),
  )
