"""The checks of a config that need neither JAX nor the data, in one place.

`python -m slotlifter_jax.main` runs `check_config` before it imports JAX, so a mistyped field
fails in a fraction of a second with one line naming it, and a multi-process launch with a bad
config fails before any process connects to the coordinator. `train.train_and_evaluate` runs the
same checks for callers that do not come through the command line. What needs the data or the
devices (the number of training scenes, the object counts of a curriculum, the device count) is
checked where those are known.

This module imports nothing of the package and no JAX: keep it that way, or the command line
pays JAX's start-up before it can report a typo.
"""

from __future__ import annotations

from typing import Optional

# validation.selection_score: what the best checkpoint maximises (docs/method.md §4).
SELECT_BY = ("nv_ari", "min_fg_nv", "psnr_novel")
# encoder.ResUNet: 4 is the paper's (features at a quarter of the input); 2 joins the stem.
OUTPUT_STRIDES = (4, 2)
SAMPLERS = ("host", "device")
# data/registry.py's readers, and the frames it can put the poses in: "world", as stored (the
# paper's), or "source_azimuth", every scene turned about the vertical axis so its (first) source
# view sits at azimuth 0 (`registry.in_source_azimuth_frame`).
DATA_FORMATS = ("uorf", "uocf", "dtu", "scannet")
FRAMES = ("world", "source_azimuth")


class ConfigError(ValueError):
  """A config that cannot train: the message names the field and what to do."""


def check_config(config) -> None:
  """Every check of this module on a whole config; ConfigError naming the first bad field."""
  train = config.train
  for problem in (masking_problem(train), rates_problem(train), selection_problem(train),
                  restarts_problem(train), averaging_problem(train), batch_problem(train),
                  sampler_problem(config), data_problem(config.data),
                  labelled_check_problem(config)):
    if problem:
      raise ConfigError(problem)
  try:
    check_supersample(config.render)  # validation renders with it
    check_output_stride(config.model.get("encoder_output_stride", 4))
    check_input_pool(config.model.get("encoder_input_pool", 1),
                     image_size=config.data.get("image_size"))
    check_stages(train.get("ray_stages", ()), field="train.ray_stages", upper=2**31 - 1,
                 multiple_of=int(train.ray_chunks))
    curriculum_stages(config.data.get("curriculum", ()))
  except ValueError as e:
    raise ConfigError(str(e)) from e


def labelled_check_problem(config) -> Optional[str]:
  """A set without masks has no ARI: the labelled early check would read made-up numbers."""
  if (config.train.get("restart_signal", "auto") == "labelled"
      and not bool(config.data.get("has_masks", True))
      and int(config.train.get("restart_check_step", 0))):
    return ("train.restart_signal='labelled' reads validation ARIs, but data.has_masks is False "
            "(this set has no masks): use 'mask_free' or 'auto'")
  return None


def data_problem(data) -> Optional[str]:
  """data.format has a reader and data.frame is one the readers can put the poses in."""
  if data.format not in DATA_FORMATS:
    return f"data.format must be one of {DATA_FORMATS}, got {data.format!r}"
  if data.get("ray_sampling", "uniform") == "floor_parallax" and data.format not in ("uorf",
                                                                                      "uocf"):
    return (f"data.ray_sampling='floor_parallax' reprojects through the floor plane z = 0 of the "
            f"uORF-style sets; data.format={data.format!r} has no such floor")
  frame = data.get("frame", "world")
  if frame not in FRAMES:
    return f"data.frame must be one of {FRAMES}, got {frame!r}"
  return None


def masking_problem(train) -> Optional[str]:
  """0 ≤ mask_min ≤ mask_max ≤ 1, or keep(t) leaves [0, 1]; the floor's release step and its
  length ≥ 0."""
  low, high = float(train.get("mask_min", 0.0)), float(train.mask_max)
  if not 0.0 <= low <= high <= 1.0:
    return (f"train.mask_min={low} and train.mask_max={high} must satisfy "
            f"0 ≤ mask_min ≤ mask_max ≤ 1")
  if int(train.get("mask_min_steps", 0)) < 0:
    return f"train.mask_min_steps={train.mask_min_steps} must be ≥ 0 (0 holds the floor for good)"
  if int(train.get("mask_min_release_steps", 0)) < 0:
    return (f"train.mask_min_release_steps={train.mask_min_release_steps} must be ≥ 0 "
            f"(0 releases the floor at once)")
  return None


def rates_problem(train) -> Optional[str]:
  """The cooldown's length and final factor, and slot attention's rate scale."""
  steps = int(train.get("lr_cooldown_steps", 0))
  if not 0 <= steps <= int(train.num_steps):
    return f"train.lr_cooldown_steps={steps} must lie in [0, train.num_steps={train.num_steps}]"
  final = float(train.get("lr_cooldown_final", 0.1))
  if not 0.0 <= final <= 1.0:
    return f"train.lr_cooldown_final={final} must lie in [0, 1]"
  scale = float(train.get("slot_attention_lr_scale", 1.0))
  if not scale >= 0.0:  # also NaN: a negative rate would climb the loss
    return f"train.slot_attention_lr_scale={scale} must be ≥ 0"
  return None


def selection_problem(train) -> Optional[str]:
  select_by = train.get("select_by", "nv_ari")
  if select_by not in SELECT_BY:
    return f"train.select_by must be one of {SELECT_BY}, got {select_by!r}"
  return None


def restarts_problem(train) -> Optional[str]:
  """The restart fields (slotlifter_jax/restarts.py): the check must fall on a validation."""
  check = int(train.get("restart_check_step", 0))
  if check < 0 or (check and check % int(train.eval_every)):
    return (f"train.restart_check_step={check} must be 0 (no check) or a multiple of "
            f"train.eval_every={train.eval_every}, a step that validates")
  if int(train.get("restarts", 0)) < 0:
    return f"train.restarts={train.restarts} must be ≥ 0"
  agreement = float(train.get("restart_min_attn_agreement", -1.0))
  if not -1.0 <= agreement <= 1.0:  # also NaN
    return (f"train.restart_min_attn_agreement={agreement} must lie in [-1, 1] (an adjusted Rand "
            f"index; -1: no such check)")
  signal = train.get("restart_signal", "auto")
  if signal not in ("auto", "labelled", "mask_free"):
    return (f"train.restart_signal={signal!r} must be 'auto', 'labelled' or 'mask_free' "
            f"(slotlifter_jax/restarts.py)")
  return None


def averaging_problem(train) -> Optional[str]:
  """The moving average's fields (slotlifter_jax/averaging.py)."""
  decay = float(train.get("ema_decay", 0.0))
  if not 0.0 <= decay < 1.0:  # also NaN
    return f"train.ema_decay is {decay}; use 0 (off) or a value in (0, 1)"
  start = int(train.get("ema_start_step", 0))
  if start < 0:
    return f"train.ema_start_step is {start}; must be ≥ 0"
  return None


def batch_problem(train) -> Optional[str]:
  """The batch's splits into gradient-accumulation chunks and ray chunks (the device count is
  checked once the devices are known)."""
  if train.batch_scenes % train.grad_accum_chunks:
    return (f"train.batch_scenes={train.batch_scenes} must be a multiple of "
            f"train.grad_accum_chunks={train.grad_accum_chunks}")
  if train.rays_per_scene % train.ray_chunks:
    return (f"train.rays_per_scene={train.rays_per_scene} must be a multiple of "
            f"train.ray_chunks={train.ray_chunks}")
  return None


def sampler_problem(config) -> Optional[str]:
  """data.sampler and what only one of the two samplers supports (the curriculum's object counts
  are checked against the training scenes once they are loaded)."""
  sampler = config.data.get("sampler", "host")
  if sampler not in SAMPLERS:
    return f"data.sampler is {sampler!r}; use one of {SAMPLERS}"
  block = int(config.train.get("steps_per_dispatch", 1))
  if sampler == "host":
    if block != 1:
      return (f"train.steps_per_dispatch={block} needs data.sampler=device (the host sampler "
              f"feeds one step per dispatch)")
    if config.data.get("curriculum", ()):
      return "data.curriculum needs data.sampler=device"
    return None
  for field, stages in (("data.scene_stages", config.data.get("scene_stages", ())),
                        ("train.ray_stages", config.train.get("ray_stages", ()))):
    if stages:
      return f"{field} needs data.sampler=host"
  if config.data.ray_sampling != "uniform":
    return f"data.ray_sampling={config.data.ray_sampling!r} needs data.sampler=host"
  if block < 1:
    return f"train.steps_per_dispatch is {block}; it must be ≥ 1"
  for field in ("log_every", "eval_every", "checkpoint_every", "num_steps"):
    if int(config.train[field]) % block:
      return (f"train.{field}={config.train[field]} is not a multiple of "
              f"train.steps_per_dispatch={block}")
  return None


def check_supersample(render) -> int:
  """`render.supersample` as an int; ValueError naming the field unless it is an integer ≥ 1."""
  value = render.get("supersample", 1)
  if isinstance(value, bool) or not isinstance(value, int) or value < 1:
    raise ValueError(f"render.supersample is {value!r}; it must be an integer ≥ 1")
  return value


def check_output_stride(stride) -> None:
  """ValueError naming `model.encoder_output_stride` unless it is one of OUTPUT_STRIDES."""
  if stride not in OUTPUT_STRIDES:
    raise ValueError(f"model.encoder_output_stride is {stride!r}; it must be one of "
                     f"{OUTPUT_STRIDES} (4 is the paper's)")


def check_input_pool(pool, *, image_size=None) -> None:
  """ValueError naming `model.encoder_input_pool` unless it is an integer ≥ 1 that divides the
  image size (when `image_size` is a known int)."""
  if isinstance(pool, bool) or not isinstance(pool, int) or pool < 1:
    raise ValueError(f"model.encoder_input_pool is {pool!r}; it must be an integer ≥ 1")
  if isinstance(image_size, int) and not isinstance(image_size, bool) and image_size % pool:
    raise ValueError(f"model.encoder_input_pool is {pool}; data.image_size {image_size} must "
                     f"divide by it")


def check_stages(stages, *, field: str, upper: int, multiple_of: int = 1
                 ) -> tuple[tuple[int, int], ...]:
  """Validates stages ((start_step, value), …) for config field `field`: start steps ≥ 0 and
  increasing, each value in [1, upper] and a multiple of `multiple_of`. Returns int pairs."""
  out = []
  for stage in stages:
    if len(stage) != 2:
      raise ValueError(f"{field}: stage {tuple(stage)!r} is not (start_step, value)")
    out.append((int(stage[0]), int(stage[1])))
  starts = [s for s, _ in out]
  if any(s < 0 for s in starts) or starts != sorted(set(starts)):
    raise ValueError(f"{field}: start steps {starts} must be ≥ 0 and strictly increasing")
  for start, value in out:
    if not 1 <= value <= upper:
      raise ValueError(f"{field}: {value} (stage from step {start}) must lie in [1, {upper}]")
    if value % multiple_of:
      raise ValueError(f"{field}: {value} (stage from step {start}) is not a multiple of "
                       f"{multiple_of}")
  return tuple(out)


def curriculum_stages(stages) -> tuple[tuple[int, int], ...]:
  """data.curriculum as int pairs (start_step, max_objects) with increasing start steps;
  ValueError naming the field otherwise (the object counts are the data's to check)."""
  out = []
  for stage in stages:
    if len(stage) != 2:
      raise ValueError(f"data.curriculum: stage {stage!r} is not (start_step, max_objects)")
    out.append((int(stage[0]), int(stage[1])))
  if [s for s, _ in out] != sorted(s for s, _ in out):
    raise ValueError(f"data.curriculum: start steps {[s for s, _ in out]} are not increasing")
  return tuple(out)
