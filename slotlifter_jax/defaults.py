"""The base configuration every data-set config in `configs/` starts from.

It holds the paper's settings for the synthetic sets (docs/method.md §1–2). A data-set config
overrides the few fields that differ (K, near/far, feature width, fine pass, …) and derives its
variants (`scene`, `paper_cpu`, `easy`, `smoke`) by overriding a few more, so no setting is
written twice.
"""

import ml_collections


def base_config() -> ml_collections.ConfigDict:
  c = ml_collections.ConfigDict()
  c.seed = 0

  # ---- model (docs/method.md §1) ----
  m = c.model = ml_collections.ConfigDict()
  m.feature_dim = 64  # D: 64 synthetic sets, 32 DTU/ScanNet
  m.encoder_stem_width = 64
  m.encoder_widths = (64, 128, 256)  # layer1..layer3 channels
  m.encoder_blocks = (3, 4, 6)  # BasicBlocks per layer: ResNet-34 layout
  # Feature map h×w = H/4×W/4 (the paper's); 2 adds a decoder stage to H/2×W/2 (encoder.py), an
  # option of this repository.
  m.encoder_output_stride = 4
  # p > 1: the encoder sees the source views box-filtered to H/p×W/p; lifting and the targets keep
  # full size (model.pooled_encoder_input), an option of this repository.
  m.encoder_input_pool = 1
  m.num_slots = 8  # K (the empty slot is extra)
  m.slot_dim = 256
  m.slot_iters = 3
  m.slot_mlp_dim = 1024
  m.slot_eps = 1.0
  m.slot_drop_path = 0.2  # stochastic depth on the slot MLP residual
  m.point_dim = 64  # width of the allocation transformer
  m.num_blocks = 4
  m.num_heads = 4
  m.self_attn_dim = 16  # per-ray self-attention projection width
  m.ffn_dim = 256
  m.max_dropout = 0.2  # residual dropout rates linspace(0, max_dropout, num_blocks)
  m.num_freqs = 10  # positional encoding frequencies 2^0..2^9
  m.colour_hidden = 64
  m.colour_layers = 4  # hidden Linear layers of the colour MLP (64→64→64→64→64→3)
  m.colour_range = "unit"  # "unit": tanh/2+1/2 in [0,1]; "signed": tanh in [-1,1] (DTU, ScanNet)
  m.density_scale = 25.0  # α = 1 − exp(−σ·δ·density_scale)
  m.density_log_init = 0.0  # initial value of the learned log density scale s_σ (official: 0)
  m.locality_box = 0.64  # |coordinate| beyond which only slots 0 and 1 may take a point
  m.remat_scan = False  # nn.scan + nn.remat over the decoder blocks: less memory, more time
  # The decoder's cross-attention and point-slot mapping, and E_p's direction half, in a folded
  # order (folded.folded_cross_attention, folded.folded_mapping, model.PointEmbedding): the same
  # parameters and function to float32 rounding, 0.90× the `scene` step and 0.87× `paper_cpu`'s.
  # Off: its rounding makes other trajectories, so the README's seed table (trained unfolded) would
  # not repeat. The one `scene` run made with it (seed 0, 2026-12-03) lost its floor after step
  # 30 000, but so did the unfolded order forked from that step (experiments/journal/2026-12.md,
  # "the late loss of the floor, forked from step 30 000"); whether the folds change how often
  # runs split is not measured.
  m.fold_products = False
  # Computation dtype: "float32", or "bfloat16" for bf16 matmuls and convolutions with float32
  # parameters, softmaxes, norm statistics, volume rendering and loss (model.py, "Numerics";
  # tolerances in tests/test_bf16.py). float32 stays the default: on this CPU (AVX-512 BF16, no
  # AMX) a prototype ran bf16 slower (docs/performance.md §2); `experiments/bench.py --dtypes`
  # measures both.
  m.dtype = "float32"
  # Ablations of docs/method.md §5 (experiments/ablations.py); the defaults are the paper's method.
  # "Without random masking" needs no switch: train.mask_max = 0 keeps every ray's features.
  m.feature_lifting = True  # False: point feature F_p = E_p only (no lifted features)
  m.density_mode = "slot"  # "slot": σ from W and A (§1.4); "mlp": a small head on h (decoder.py)

  # ---- rendering (docs/method.md §1.5) ----
  r = c.render = ml_collections.ConfigDict()
  r.near = 6.0 / 7.0
  r.far = 20.0 / 7.0
  r.num_samples = 96
  r.num_fine_samples = 0  # 0: no fine pass (synthetic sets); 64 for DTU/ScanNet
  # () or (z_min, z_max) in the normalised frame: each ray is sampled only where it crosses that
  # horizontal slab (model.SlotLifter.ray_interval). () = all of [near, far] (the paper's).
  r.z_bounds = ()
  r.chunk = 4096  # rays per chunk when rendering a full view
  # Full views (eval, validation, pictures) average S×S rays per pixel on a regular grid inside it,
  # as the embedded set's pixels are made (rendering/views.py); S² times the work. 1: one ray
  # through the centre, the paper's.
  r.supersample = 1
  # Adaptive full-view rendering in --mode=eval and --mode=render (slotlifter_jax/rendering/adaptive.py,
  # docs/performance.md): the decoder runs the whole grid on every stride-th pixel only and a window of
  # `adaptive_window` grid samples elsewhere. Off: every pixel on the whole grid (exact).
  r.adaptive = False
  r.adaptive_stride = 3  # proposal pixels every stride-th row and column (+ the last ones)
  r.adaptive_window = 24  # samples per non-proposal pixel (≤ num_samples)
  r.adaptive_mass_eps = 0.01  # render weight a proposal's significant range may leave out
  r.adaptive_fallback = True  # a pixel whose neighbours' ranges overflow the window: whole grid

  # ---- data (docs/method.md §3) ----
  d = c.data = ml_collections.ConfigDict()
  d.format = "uorf"  # uorf | uocf | dtu | scannet
  d.root = ""  # empty: the embedded default set, generated once into the cache folder
  d.family = "clevr"  # embedded generator family when root is empty
  d.subset = "clevr_567"  # uORF folder prefix: <root>/<subset>_{train,val,test}
  d.scene_scale = 1.0 / 7.0  # uORF "nss_scale"
  d.image_size = 128  # generated / loaded resolution (reader resizes when smaller than on disk)
  d.num_source_views = 1  # V
  d.views_per_scene = 4
  d.num_train_scenes = 1000
  d.num_val_scenes = 100
  d.num_test_scenes = 100
  # Embedded generator only: the development split, the scenes that were the test split before a
  # held-out one was drawn (data/layout.py, SPLITS). Probes may read it; no choice reads test.
  d.num_dev_scenes = 100
  # Embedded generator only: objects per scene (0: the family's default, CLEVR 5–7, room 1–4) and
  # a factor on every CLEVR object's size (capped at 2 to fit the default footprint). An easy set,
  # e.g. 1–3 objects at 1.6×, tells a data problem from a model one; it gets its own cache folder.
  d.min_objects = 0
  d.max_objects = 0
  d.object_scale = 1.0
  # Embedded room set only: the same scenes with untextured floor and walls (its own cache folder),
  # the ladder's rung between a texture problem and a chair one.
  d.plain_background = False
  d.plain_objects = False  # and the chairs in one colour each, legs included
  d.no_walls = False  # and no walls: the floor runs to the horizon, as in the clevr family
  # and each chair as drawn ("chairs"), its legs filled in ("solid") or one box ("boxes"): the
  # rungs between thin parts and compact objects; or the room holding CLEVR's objects ("clevr",
  # counted by min/max_objects as CLEVR's, 5–7 by default), the rung between the room's
  # background and its objects (data/layout.py, ROOM_OBJECTS)
  d.room_objects = "chairs"
  d.grey_floor = False  # and every scene on the clevr family's grey floor: one floor for all scenes
  d.novel_ray_prob = 0.75  # probability that a scene's rays come from novel views only
  # "uniform" (paper) or "contrast": a share `contrast_mix` of the rays drawn towards pixels far
  # from their view's median colour (data/pipeline.py says why and what it changes).
  d.ray_sampling = "uniform"
  d.contrast_mix = 0.5
  d.has_masks = True
  # () or (z_min, z_max): the horizontal slab of the normalised frame that holds the scene (from
  # just below the floor to above the tallest object), for sets that have one. Variants that
  # sample only inside the scene copy it to render.z_bounds.
  d.scene_z_range = ()
  # "world": poses as stored (the paper's). "source_azimuth": each scene turned about the vertical
  # axis so its source view sits at azimuth 0 (data/registry.py), for sets whose source cameras
  # stand at random azimuths around a z-up scene centred at the origin (uORF sets, the embedded
  # set). Without it a position in the frame says nothing about where it appears in the source
  # view until the model has inferred the source camera's azimuth from the image.
  d.frame = "world"
  # "host": NumPy batches on a thread (every format). "device": the training split kept on the
  # device and each batch drawn inside the jitted step (fixed-source sets, uniform rays; see
  # data/device_sampler.py), which also allows several steps per dispatch.
  d.sampler = "host"
  # Object-count curriculum ((start_step, max_objects), …), device sampler only: from each start
  # step on only training scenes with at most max_objects objects are drawn. () = off.
  d.curriculum = ()
  # Training scenes by step ((start_step, num_scenes), …), host sampler only: from each start step
  # on, batches come from the first num_scenes training scenes; before the first stage and with
  # () from all of them (data/pipeline.py). Grows the set once the slots have settled.
  d.scene_stages = ()

  # ---- training (docs/method.md §2) ----
  t = c.train = ml_collections.ConfigDict()
  t.num_steps = 250_000
  t.batch_scenes = 4
  t.rays_per_scene = 1024
  # Rays per scene by step ((start_step, rays), …), host sampler only: from each start step on,
  # that many rays; before the first stage and with (), rays_per_scene (data/pipeline.py).
  t.ray_stages = ()
  t.base_lr = 5e-5
  t.lr_floor = 0.02
  t.warmup_steps = 10_000
  t.decay_steps = 50_000  # half-life of the exponential decay
  # Both rates times a cosine from 1 down to lr_cooldown_final over the last lr_cooldown_steps
  # steps of num_steps (0: none, the paper's). Not in the paper: for runs whose rate is held
  # near its base to the end (schedules.cooldown_factor).
  t.lr_cooldown_steps = 0
  t.lr_cooldown_final = 0.1
  # Not in the paper: slot attention's parameters follow the backbone schedule times this factor
  # (1: the paper's, one schedule for the whole backbone). At base rate 1e-4 every run that lost
  # the floor had it shared out already in slot attention's own grouping (`attn_ari` ≤ 0.07),
  # while the gain in FG-ARI over 5e-5 comes from the decoder (experiments/journal/2026-11.md,
  # "the floor, from the locality box to slot attention"; docs/fast_model.md §3).
  t.slot_attention_lr_scale = 1.0
  # "lion" (paper) or "adamw" (Lion moves every weight by ±lr each step whatever the gradient's
  # size; AdamW was tried for the small paper_cpu batch and fitted one scene no faster:
  # docs/quick_model.md).
  t.optimizer = "lion"
  t.b1 = 0.9
  t.b2 = 0.99  # Lion's β2
  t.adam_b2 = 0.999  # AdamW's β2 (only with optimizer = "adamw")
  t.weight_decay = 1e-3
  t.grad_clip = 0.5
  t.mask_anneal_steps = 30_000  # masking ratio 0.99 → 0
  t.mask_max = 0.99
  # Masking ratio the anneal ends at and holds (0: the paper's, every ray keeps its lifted features
  # after mask_anneal_steps). Not in the paper: slot attention's grouping rises while rays are
  # masked and fades once none are (experiments/journal/2026-11.md, "a masking floor";
  # docs/fast_model.md §3). Evaluation never masks.
  t.mask_min = 0.0
  t.mask_min_steps = 0  # the floor holds until this step, then every ray keeps its features (0: never)
  t.mask_min_release_steps = 0  # lower the floor to 0 along a cosine over this many steps (0: at once)
  # What the best checkpoint maximises on validation: "nv_ari", "min_fg_nv" (the worse of FG-ARI
  # and NV-ARI) or "psnr_novel"; sets without masks always use novel-view PSNR (docs/method.md §4).
  t.select_by = "nv_ari"
  t.noise_anneal_steps = 30_000  # slot init noise σ 1 → 0
  t.locality_steps = 50_000  # locality constraint on for the first N steps (0: never)
  t.max_nonfinite_in_row = 20
  # Not in the paper: an exponential moving average of the parameters with this decay (0: off),
  # tracking them exactly until `ema_start_step` updates; validation, evaluation and rendering then
  # use the average (slotlifter_jax/averaging.py).
  t.ema_decay = 0.0
  t.ema_start_step = 0
  # Restart a run from a new seed (seed + 1000) at most this many times, when validation flags it
  # as collapsed after the masking and slot-noise schedules, or when its selection score
  # (`select_by`) is below `restart_min_score` at step `restart_check_step` (0: no such check).
  # The abandoned attempt is kept under DIR/restarted/ (slotlifter_jax/restarts.py).
  t.restarts = 0
  t.restart_check_step = 0
  t.restart_min_score = 0.0
  # Which early check: "labelled" (the selection score, needs masks), "mask_free" (slots in use on
  # the validation views, `validation.mask_free_statistics`), or "auto": labelled when the
  # validation scenes have masks, else mask-free (slotlifter_jax/restarts.py).
  t.restart_signal = "auto"
  t.restart_min_active_slots = 0.0
  # and, mask-free, the mean per-pixel slot entropy / log K above which a spread slot split (a floor
  # shared by several slots) restarts the attempt; 1: never
  t.restart_max_pixel_entropy = 1.0
  # and, mask-free, the adjusted Rand index between slot attention's grouping of the validation
  # source views and the rendered split of them below which the attempt restarts; −1: never
  t.restart_min_attn_agreement = -1.0
  t.log_every = 50
  t.eval_every = 5000
  t.eval_scenes = 8  # validation scenes used at each evaluation interval
  t.checkpoint_every = 2000
  # Train steps per dispatch under lax.scan (data.sampler = "device" only); log_every,
  # eval_every, checkpoint_every and num_steps must be multiples of it.
  t.steps_per_dispatch = 1
  t.keep_checkpoints = 3
  # Scenes of a batch are split into this many chunks inside the step and their gradients averaged
  # (same gradient, a fraction of the activation memory): in one piece the paper's 4 × 1024 rays ×
  # 96 samples need about twice the temporaries of bench config A; two chunks fit a 24 GB
  # machine (docs/performance.md §4).
  t.grad_accum_chunks = 2
  # …and the rays of each chunk into this many parts (memory mode: docs/performance.md).
  t.ray_chunks = 1
  # Random-bit generator of every training key. "unsafe_rbg" makes dropout/masking bits cheaper
  # (threefry dropout masks were a large share of a CPU step: docs/performance.md §2) and compiles
  # faster; both are deterministic in (seed, step), so resumes stay exact.
  t.prng_impl = "threefry2x32"
  return c


# Former variant names: `fast` was the scene-sized model, `quick` the paper's model at CPU widths.
RENAMED = {"fast": "scene", "quick": "paper_cpu"}


def apply_variant(c: ml_collections.ConfigDict, variant: str) -> ml_collections.ConfigDict:
  """Derives a variant from a data-set config by overriding a few fields (never by copying).

  Variants compose left to right with '+', e.g. `clevr.py:scene+easy`. A former name is refused
  with its new one (RENAMED), so a command that used it fails instead of training something else.
  """
  if variant in ("", "paper"):
    return c
  known = {"scene": scene, "paper_cpu": paper_cpu, "smoke": smoke, "easy": easy}
  for name in variant.split("+"):
    if name in RENAMED:
      raise ValueError(f"variant {name!r} was renamed {RENAMED[name]!r}; use the new name")
    if name not in known:
      raise ValueError(f"unknown variant {name!r}: use '', 'paper' or a '+'-joined list of "
                       f"{sorted(known)}")
    c = known[name](c)
  return c


def _share(steps, num: int, den: int, multiple_of=1):
  """round(steps · num / den) steps (halves up), rounded to a multiple of `multiple_of`, as a
  reference that follows `steps` (the FieldReference of train.num_steps) and `multiple_of` (an int
  or a FieldReference, e.g. of train.eval_every).

  A variant's schedule lengths thus stay the same shares of its budget however the command line
  sets train.num_steps, and a field the command line sets itself replaces its reference (a
  resolved copy, e.g. DIR/config.json, holds plain numbers). Integer arithmetic, so the variant's
  own budget gives exactly its step counts.
  """
  return (steps * (2 * num) + den * multiple_of) // (2 * den * multiple_of) * multiple_of


def paper_cpu(c):
  """The paper's model and method shrunk to a CPU (formerly `quick`): 64×64, a narrower
  ResNet-18-style encoder, fewer rays and samples, every schedule compressed to 6500 steps.

    python -m slotlifter_jax.main --config=configs/clevr.py:paper_cpu --workdir=DIR

  Expected (best checkpoint, 100 scenes of the former test split): novel-view PSNR 22.81 dB,
  FG-ARI 0.172, NV-ARI 0.654 (`experiments/results/clevr_quick_test_metrics.json`): it renders the
  scene but does not split it. Time: 6500 steps in 59 min 20 s on the project's 2-core CPU,
  shared with other jobs for the first 27 min. Why each setting is what it is, and what did not
  help: docs/quick_model.md.
  """
  c.data.image_size = 64
  c.data.num_train_scenes = 1000
  c.data.num_val_scenes = 100
  c.data.num_test_scenes = 100
  c.model.encoder_blocks = (2, 2, 2)
  c.model.encoder_widths = (32, 64, 128)
  c.model.encoder_stem_width = 32
  c.model.feature_dim = 32
  c.render.num_samples = 32
  # Adaptive rendering (off by default): the setting experiments/bench_render.py picked for the
  # trained model (×1.3 at −0.06 dB; experiments/journal/2026-11.md, "Adaptive full-view
  # rendering").
  c.render.adaptive_stride = 4
  c.render.adaptive_window = 16
  c.train.num_steps = 6500
  c.train.batch_scenes = 2
  c.train.rays_per_scene = 256
  c.train.grad_accum_chunks = 1
  # A more opaque start or a higher rate left every run in a "fog" at the near plane
  # (docs/quick_model.md).
  c.model.density_log_init = -3.0
  c.train.base_lr = 5e-5
  # Every schedule a fixed share of the budget (`_share`): 200, 4000, 3000, 3000 and 4000 of the
  # 6500 steps, and the same shares of any --config.train.num_steps.
  n = c.train.get_ref("num_steps")
  c.train.warmup_steps = _share(n, 2, 65)
  c.train.decay_steps = _share(n, 8, 13)
  c.train.mask_anneal_steps = _share(n, 6, 13)
  c.train.noise_anneal_steps = _share(n, 6, 13)
  c.train.locality_steps = _share(n, 8, 13)
  c.train.eval_every = 1000
  c.train.checkpoint_every = 250
  c.train.prng_impl = "unsafe_rbg"
  return c


def smoke(c):
  """About a minute on a 2-core CPU: proves that the whole command works, learns nothing."""
  c.data.image_size = 32
  c.data.num_train_scenes = 4
  c.data.num_val_scenes = 2
  c.data.num_test_scenes = 2
  c.data.num_dev_scenes = 2
  c.model.encoder_blocks = (1, 1, 1)
  c.model.encoder_widths = (8, 16, 16)
  c.model.encoder_stem_width = 8
  c.model.feature_dim = 8
  c.model.num_slots = 4
  c.model.slot_dim = 32
  c.model.slot_mlp_dim = 64
  c.model.point_dim = 16
  c.model.num_blocks = 2
  c.model.ffn_dim = 32
  c.model.self_attn_dim = 8
  c.model.colour_hidden = 16
  c.render.num_samples = 8
  c.render.chunk = 512
  c.train.num_steps = 6
  c.train.batch_scenes = 2
  c.train.rays_per_scene = 32
  c.train.grad_accum_chunks = 1
  c.train.warmup_steps = 2
  c.train.decay_steps = 10
  c.train.mask_anneal_steps = 3
  c.train.noise_anneal_steps = 3
  c.train.locality_steps = 3
  c.train.log_every = 2
  c.train.eval_every = 3
  c.train.eval_scenes = 1
  c.train.checkpoint_every = 3
  return c


def scene(c):
  """The scene-sized headline model (formerly `fast`): `paper_cpu`'s method and loss with no more
  model than a 64 px CLEVR scene needs; the README's training command.

    python -m slotlifter_jax.main --config=configs/clevr.py:scene --workdir=DIR

  Expected (best checkpoint with the moving average, 100 scenes of the development split, the
  former test split): FG-ARI and NV-ARI ≥ 0.8 on five seeds of five, novel-view PSNR about 26 dB
  (the README's results table, from `experiments/results/clevr_fast50k_*_test_metrics.json`; held
  out: `experiments/results/headline_clevr.json` once evaluated). Time: 46–64 min for the 50 000
  steps on the reference host (a 2-core AMD EPYC VM); a failed check adds 14 000 steps. Each cut,
  what it saves and what it costs, and the probes behind the recipe: docs/fast_model.md.
  """
  if not tuple(c.data.get("scene_z_range", ())):
    raise ValueError(f"variant 'scene' samples rays only inside data.scene_z_range, which this "
                     f"config (data.format={c.data.format!r}, data.subset={c.data.subset!r}) "
                     f"leaves empty: configs/clevr.py and configs/room_chair.py set it")
  c = paper_cpu(c)
  c.model.slot_dim = 32
  c.model.slot_mlp_dim = 64
  c.model.point_dim = 32
  c.model.num_blocks = 2
  c.model.ffn_dim = 64
  c.model.colour_hidden = 32
  c.render.num_samples = 16
  c.render.z_bounds = tuple(c.data.scene_z_range)
  c.train.batch_scenes = 4
  c.train.rays_per_scene = 128
  c.data.sampler = "host"
  c.train.steps_per_dispatch = 1
  c.data.frame = "source_azimuth"
  c.data.ray_sampling = "contrast"
  # Every schedule a fixed share of the budget (`_share`), so --config.train.num_steps=N moves
  # them all and a field set explicitly keeps its value. At 50 000 steps: warm-up 500, a
  # half-life of 200 000 (the rate held near its base to the end), masking, slot noise and
  # locality over 20 000, the masking floor to 40 000 and released over the last 10 000, the
  # average from the release's start, and the restart check at 14 000 (on eval_every's grid).
  n, every = c.train.get_ref("num_steps"), c.train.get_ref("eval_every")
  c.train.num_steps = 50_000
  c.train.warmup_steps = _share(n, 1, 100)
  c.train.decay_steps = n * 4
  c.train.mask_anneal_steps = _share(n, 2, 5)
  c.train.noise_anneal_steps = _share(n, 2, 5)
  c.train.locality_steps = _share(n, 2, 5)
  c.train.mask_min = 0.5
  c.train.mask_min_steps = _share(n, 4, 5)
  c.train.mask_min_release_steps = _share(n, 1, 5)
  c.train.select_by = "min_fg_nv"
  c.train.ema_decay = 0.999
  c.train.ema_start_step = _share(n, 4, 5)
  c.train.base_lr = 1e-4
  c.train.slot_attention_lr_scale = 2.0
  c.train.restarts = 2
  c.train.restart_check_step = _share(n, 7, 25, multiple_of=every)
  c.train.restart_min_score = 0.55
  c.train.restart_min_active_slots = 3.0
  # Fitted on the validation logs that record the mask-free statistics at step 14 000
  # (experiments/journal/2026-12.md, "A mask-free check that reads the spread floor"): the runs
  # the labelled check keeps read ≤ 0.24; those it restarts that have 3+ slots in use, their floor
  # spread over them, ≥ 0.41; the gap's middle.
  c.train.restart_max_pixel_entropy = 0.33
  c.train.log_every = 50
  c.train.eval_every = 2000
  c.train.eval_scenes = 20
  c.train.checkpoint_every = 1000
  return c


def easy(c):
  """The ladder's lower rung: 1–3 CLEVR objects at 1.6× size instead of 5–7 (its own embedded
  set). A model that cannot split these has a defect, not too small a budget."""
  c.data.min_objects = 1
  c.data.max_objects = 3
  c.data.object_scale = 1.6
  return c
