"""The tables of docs/rooms.md, from the room runs' files under experiments/results/.

Written and checked by experiments/tables.py with every other table (`--print=room_val100`,
`--print=room_curves`). Standard library only.

- room_val100: the `--mode=eval --split=val` evaluations on all 100 validation scenes
  (`room_probe_*_val100_metrics.json`, with their per-scene rows for the split by object count);
- room_curves: the validation logs the runs wrote while training (`room_probe_*_val_metrics.jsonl`,
  20 scenes each), at fixed steps;
- room_slot_routing: each chair followed through slot attention and the rendering
  (`room_slot_routing_*.json`, written by experiments/slot_routing.py);
- room_depth_placement: where the novel views put what the source view sees, against the true
  depth (`room_depth_placement_*.json`, written by experiments/depth_placement.py).
"""

from __future__ import annotations

import csv
import json
import math
import os
import statistics

from experiments import table_common as tc

# (label, run name): RESULTS/<name>_val100_metrics.json and <name>_val100_per_scene.csv.
ROOM_VAL100 = (
    ("textured boxes at 0.6, 64 px", "room_probe_boxes_x06_parallax"),
    ("chairs, 64 px", "room_probe_chairs_parallax"),
    ("chairs, 128 px (seed 0)", "room_probe_chairs_128px_parallax"),
    ("chairs, 128 px (seed 5)", "room_probe_chairs_128px_seed5_parallax"),
    ("chairs, 128 px, slot noise to step 50 000 (seed 5, AMD host)",
     "room_probe_chairs_128px_noise50k_seed5_amd_parallax"),
    ("the same, 32 samples per ray from step 40 000",
     "room_probe_chairs_128px_noise50k_s32from40k_seed5_amd_parallax"),
    ("the same, rates cooled to 0.1× over steps 42 000–50 000",
     "room_probe_chairs_128px_noise50k_cool8k_seed5_amd_parallax"),
)

# (label, run name): RESULTS/<name>_val_metrics.jsonl. Every run is the room recipe
# (`configs/room_chair.py:scene`, K = 5, 1–4 objects unless the label names a count) at the size and
# with the overrides its label names, one attempt each (no restart).
ROOM_CURVES = (
    ("CLEVR's objects, 64 px", "room_probe_clevr_objects_1to4_k5_parallax"),
    ("textured boxes at 0.6, 64 px", "room_probe_boxes_x06_parallax"),
    ("chairs at 0.6, 64 px", "room_probe_chairs_x06_parallax"),
    ("chairs, 64 px", "room_probe_chairs_parallax"),
    ("chairs, 64 px, 32×32 feature map", "room_probe_chairs_stride2_parallax"),
    ("chairs, 64 px, wide encoder (D = 64)", "room_probe_chairs_wide_encoder_parallax"),
    ("chairs, 64 px, wide slots (128)", "room_probe_chairs_wide_slots_parallax"),
    ("chairs, 128 px targets, 64 px encoder", "room_probe_chairs_128px_pool2_parallax"),
    ("chairs, 128 px, seed 0", "room_probe_chairs_128px_parallax"),
    ("chairs, 128 px, seed 1", "room_probe_chairs_128px_seed1_parallax"),
    ("chairs, 128 px, seed 2", "room_probe_chairs_128px_seed2_parallax"),
    ("chairs, 128 px, seed 3", "room_probe_chairs_128px_seed3_parallax"),
    ("chairs, 128 px, seed 4", "room_probe_chairs_128px_seed4_parallax"),
    ("chairs, 128 px, seed 5", "room_probe_chairs_128px_seed5_parallax"),
    ("chairs, 128 px, seed 6", "room_probe_chairs_128px_seed6_parallax"),
    ("chairs, 128 px, seed 1, contrast_mix 0.8", "room_probe_chairs_128px_mix08_seed1_parallax"),
    ("chairs, 128 px, seed 3, contrast_mix 0.8", "room_probe_chairs_128px_mix08_seed3_parallax"),
    ("chairs, 128 px, seed 1, slot noise to step 50 000",
     "room_probe_chairs_128px_noise50k_seed1_parallax"),
    ("chairs, 128 px, seed 5, slot noise to step 50 000",
     "room_probe_chairs_128px_noise50k_seed5_parallax"),
    ("chairs, 128 px, seed 5, slot noise to step 50 000, off from step 16 000",
     "room_probe_chairs_128px_noise50k_off16k_seed5_parallax"),
    ("chairs, 128 px, seed 6, slot noise to step 50 000",
     "room_probe_chairs_128px_noise50k_seed6_parallax"),
    ("chairs, 128 px, seed 6, slot noise to step 50 000, no locality constraint",
     "room_probe_chairs_128px_noise50k_nolocality_seed6_parallax"),
    ("chairs, 128 px, seed 6, slot noise to step 50 000, 4 decoder blocks",
     "room_probe_chairs_128px_noise50k_blocks4_seed6_parallax"),
    ("chairs, 128 px, seed 6, slot noise to step 50 000, decoder width 64",
     "room_probe_chairs_128px_noise50k_width64_seed6_parallax"),
    ("chairs, 128 px, seed 6, slot noise to step 50 000, 32 samples per ray",
     "room_probe_chairs_128px_noise50k_samples32_seed6_parallax"),
    ("chairs, 128 px, seed 1, slot noise to step 50 000, 32 samples per ray",
     "room_probe_chairs_128px_noise50k_samples32_seed1_parallax"),
    ("chairs, 128 px, seed 5, slot noise to step 50 000, 32 samples per ray",
     "room_probe_chairs_128px_noise50k_samples32_seed5_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000",
     "room_probe_chairs_128px_noise50k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise and locality constraint to step 50 000",
     "room_probe_chairs_128px_noise50k_loc50k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000, 32 samples per ray from "
     "step 40 000", "room_probe_chairs_128px_noise50k_s32from40k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000, rates cooled to 0.1× "
     "over steps 42 000–50 000", "room_probe_chairs_128px_noise50k_cool8k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000, 256 rays per scene from "
     "step 28 000 (forked from the run with the locality constraint to step 50 000)",
     "room_probe_chairs_128px_noise50k_rays256from28k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000, no masking floor from "
     "step 28 000 (forked from the run with the locality constraint to step 50 000)",
     "room_probe_chairs_128px_noise50k_nomaskfrom28k_seed5_amd_parallax"),
    ("chairs, 128 px, seed 5 on the AMD host, slot noise to step 50 000, s_σ starting at 0 (the "
     "paper's value)", "room_probe_chairs_128px_noise50k_dens0_seed5_amd_parallax"),
    ("4 chairs in every scene, 128 px, seed 1", "room_probe_chairs4_128px_seed1_parallax"),
    ("4 chairs in every scene, 128 px, seed 3", "room_probe_chairs4_128px_seed3_parallax"),
)
CURVE_STEPS = (4000, 8000, 14000, 20000, 30000, 50000)
CURVE_KEYS = ("fg_ari_multi", "nv_ari", "attn_fg_ari")
# The mask-free agreement of slot attention's grouping with the rendered split of the source view
# (validation.mask_free_statistics), early: it parted the first five 128 px seeds from step 2000
# but not seeds 5 and 6 (docs/rooms.md §4), so the table shows it beside the ARIs, not as a rule.
AGREEMENT_STEPS = (2000, 4000, 6000, 8000, 14000)


def _by_count(name: str, metric: str) -> dict[int, tuple[float, float]]:
  """{object count: (mean, standard error)} of one metric over the per-scene rows."""
  path = os.path.join(tc.RESULTS, name)
  try:
    with open(path, encoding="utf-8", newline="") as f:
      rows = list(csv.DictReader(f))
  except OSError as e:
    raise tc.TableError(f"experiments/results/{name}: cannot read ({e.strerror})") from None
  groups: dict[int, list[float]] = {}
  for row in rows:
    if "num_objects" not in row or metric not in row:
      raise tc.TableError(f"experiments/results/{name}: no num_objects or {metric} column")
    value = float(row[metric])
    if not math.isnan(value):
      groups.setdefault(int(float(row["num_objects"])), []).append(value)
  return {n: (statistics.mean(v), statistics.stdev(v) / math.sqrt(len(v)) if len(v) > 1 else 0.0)
          for n, v in sorted(groups.items())}


def _val_record(name: str) -> dict:
  """RESULTS/<name>, refused unless it read the validation split."""
  d = tc.load_json(name)
  if d.get("split") != "val":
    raise tc.TableError(f"experiments/results/{name}: split {d.get('split')!r}, not 'val': no "
                        f"room choice reads another split")
  return d


def _hosts(records) -> str:
  """The distinct hosts the records were computed on, in order, joined by '; '."""
  return "; ".join(dict.fromkeys(tc.described_host(r.get("provenance") or {})
                                 or "a host not recorded" for r in records))


def _metrics(record: dict, name: str, keys, field: str = "metrics") -> dict:
  """The record's `field` (its metrics), refused in one line when one of `keys` is missing (an
  evaluation written before the region split, or of a set without depth maps)."""
  m = record.get(field) or {}
  missing = [k for k in keys if k not in m]
  if missing:
    raise tc.TableError(f"experiments/results/{name}: no {', '.join(missing)} in its {field}")
  return m


def room_val100() -> list[str]:
  """docs/rooms.md: each room run's best checkpoint on all 100 validation scenes."""
  rows = ["| run | checkpoint | FG-ARI | FG-ARI, ≥ 2 objects | NV-ARI | novel PSNR (dB) | "
          "PSNR (dB): source / novel, seen / novel, unseen | "
          "FG-ARI ≥ 2 objects by count: 2 / 3 / 4 | slots in use by count: 1 / 2 / 3 / 4 |",
          "|---|---|---|---|---|---|---|---|---|"]
  names, records = [], []
  for label, run in ROOM_VAL100:
    name, scenes = f"{run}_val100_metrics.json", f"{run}_val100_per_scene.csv"
    d = _val_record(name)
    m = _metrics(d, name, ("fg_ari", "fg_ari_multi", "nv_ari", "psnr_novel", "psnr_source",
                           "psnr_novel_seen", "psnr_novel_unseen"))
    cell = lambda k, f="{:.3f}": f"{f.format(m[k]['mean'])} ± {f.format(m[k]['stderr'])}"
    fg = _by_count(scenes, "fg_ari_multi")
    slots = _by_count(scenes, "active_slots")
    rows.append(f"| {label} | step {d['checkpoint']['step']}, {d['parameters']} | {cell('fg_ari')} | "
                f"{cell('fg_ari_multi')} | {cell('nv_ari')} | {cell('psnr_novel', '{:.2f}')} | "
                + " / ".join(f"{m[k]['mean']:.1f}" for k in
                             ("psnr_source", "psnr_novel_seen", "psnr_novel_unseen")) + " | "
                + " / ".join(f"{fg[n][0]:.2f}" for n in sorted(fg)) + " | "
                + " / ".join(f"{slots[n][0]:.1f}" for n in sorted(slots)) + " |")
    names += [name, scenes]
    records.append(d)
  return rows + ["", "Split: validation, 100 scenes (the split every room choice reads; the "
                 "held-out test split is not read until a recipe splits the set). ± : the standard "
                 "error over the scenes. Checkpoint: the best by validation, `average` = the moving "
                 "average of the parameters. Seen / unseen: the novel views' pixels whose surface "
                 "the source view sees / does not see (by the true depth maps). FG-ARI on a "
                 "one-object view is 1 or 0 (docs/method.md §4), so the columns after NV-ARI "
                 "split the scenes by their object count. "
                 f"Evaluated on {_hosts(records)}.", tc.files_line(names)]


def _val_rows(name: str) -> dict[int, dict]:
  """Validation rows by step; a step validated again after a resume keeps its last row."""
  path = os.path.join(tc.RESULTS, name)
  try:
    with open(path, encoding="utf-8") as f:
      records = [json.loads(line) for line in f if line.strip()]
  except OSError as e:
    raise tc.TableError(f"experiments/results/{name}: cannot read ({e.strerror})") from None
  except json.JSONDecodeError as e:
    raise tc.TableError(f"experiments/results/{name}: not JSON lines ({e.msg})") from None
  return {int(r["step"]): r for r in records
          if r.get("kind", "val") == "val" and all(k in r for k in CURVE_KEYS)}


def room_curves() -> list[str]:
  """docs/rooms.md: the room runs' validation during training at fixed steps."""
  rows = ["| run | " + " | ".join(f"{s // 1000}k" for s in CURVE_STEPS) + " | last validation | "
          "agreement " + " / ".join(f"{s // 1000}k" for s in AGREEMENT_STEPS) + " |",
          "|---|" + "---|" * (len(CURVE_STEPS) + 2)]
  names = []
  for label, run in ROOM_CURVES:
    name = f"{run}_val_metrics.jsonl"
    by_step = _val_rows(name)
    if not by_step:
      raise tc.TableError(f"experiments/results/{name}: no validation with {', '.join(CURVE_KEYS)}")
    cell = lambda step: " / ".join(f"{by_step[step][k]:.2f}" for k in CURVE_KEYS)
    cells = ["–" if s not in by_step else cell(s) for s in CURVE_STEPS]
    agreement = " / ".join(f"{by_step[s]['mf_attn_agreement']:.2f}"
                           if "mf_attn_agreement" in by_step.get(s, {}) else "–"
                           for s in AGREEMENT_STEPS)
    # The last validation in full: runs stopped between the fixed steps (forks compared after
    # their fork step) differ there and nowhere else in the row.
    last = max(by_step)
    rows.append(f"| {label} | " + " | ".join(cells) + f" | {last}: {cell(last)} | {agreement} |")
    names.append(name)
  return rows + ["", "Each cell: FG-ARI on scenes of ≥ 2 objects / NV-ARI / slot attention's own "
                 "FG-ARI of the source view, on 20 validation scenes while training (–: the run "
                 "stopped before that step); the last validation: its step and the same three. "
                 "Agreement: the adjusted Rand index between slot attention's "
                 "grouping of the source view and the rendered split of it, read from the model's "
                 "outputs alone (no mask). Every run is `configs/room_chair.py:scene` (K = 5, "
                 "1–4 objects; a row that names a count trains and validates on scenes of that "
                 "count) at the size and with the overrides of its row, without the restart "
                 "check (each row one attempt), seed 0 unless named. The logs record "
                 "no machine: every run was trained on a 2-core Intel Xeon with AVX-512 and AMX "
                 "except the rows that name the AMD host, a 2-core AMD EPYC with AVX-512 and no "
                 "AMX (experiments/journal/2026-12.md, the sections \"Textured rooms: …\"). The "
                 "same seed does not retrace its run on another host, so a row's seed names its "
                 "scenes' order and its initial values, not its outcome.",
                 tc.files_line(names)]


# (label, file): RESULTS/<file>.json from `python experiments/slot_routing.py --workdir=DIR
# --checkpoint=latest --params=trained --scenes=100 --out=...` on the 128 px seeds' runs.
ROOM_SLOT_ROUTING = (
    ("seed 2", "room_slot_routing_chairs_128px_seed2_step28633"),
    ("seed 5", "room_slot_routing_chairs_128px_seed5_step36558"),
    ("seed 5", "room_slot_routing_chairs_128px_seed5_step50000"),
    ("seed 6", "room_slot_routing_chairs_128px_seed6_step16507"),
    ("seed 3", "room_slot_routing_chairs_128px_seed3_step8208"),
    ("seed 4", "room_slot_routing_chairs_128px_seed4_step6141"),
    ("seed 1, slot noise to step 50 000", "room_slot_routing_chairs_128px_noise50k_seed1_step16308"),
    ("seed 5, slot noise to step 50 000", "room_slot_routing_chairs_128px_noise50k_seed5_step16000"),
    ("seed 5, slot noise to step 50 000", "room_slot_routing_chairs_128px_noise50k_seed5_step27132"),
    ("seed 5, slot noise to step 50 000, off from step 16 000",
     "room_slot_routing_chairs_128px_noise50k_off16k_seed5_step24473"),
    ("seed 6, slot noise to step 50 000", "room_slot_routing_chairs_128px_noise50k_seed6_step16000"),
    ("seed 6, slot noise to step 50 000, no locality constraint",
     "room_slot_routing_chairs_128px_noise50k_nolocality_seed6_step12000"),
    ("seed 6, slot noise to step 50 000, 4 decoder blocks",
     "room_slot_routing_chairs_128px_noise50k_blocks4_seed6_step16000"),
    ("seed 6, slot noise to step 50 000, decoder width 64",
     "room_slot_routing_chairs_128px_noise50k_width64_seed6_step14000"),
    ("seed 6, slot noise to step 50 000, 32 samples per ray",
     "room_slot_routing_chairs_128px_noise50k_samples32_seed6_step14000"),
    ("seed 1, slot noise to step 50 000, 32 samples per ray",
     "room_slot_routing_chairs_128px_noise50k_samples32_seed1_step16000"),
    ("seed 5 on the AMD host, slot noise to step 50 000",
     "room_slot_routing_chairs_128px_noise50k_seed5_amd_step28000"),
    ("seed 5 on the AMD host, slot noise and locality constraint to step 50 000",
     "room_slot_routing_chairs_128px_noise50k_loc50k_seed5_amd_step28000"),
)


def _dropped_cell(run: str, kept: dict) -> tuple[str, list[str]]:
  """The cell of `run`'s checkpoint rendered without lifted features and the file it read, if
  computed; that file must hold the same checkpoint on the same scenes."""
  name = f"{run}_dropped.json"
  if not os.path.exists(os.path.join(tc.RESULTS, name)):
    return "–", []
  d = _val_record(name)
  if d.get("lifted") != "dropped" or d["step"] != kept["step"] or d["scenes"] != kept["scenes"]:
    raise tc.TableError(f"experiments/results/{name}: not {run}.json's checkpoint and scenes "
                        f"rendered with --lifted=dropped")
  s = d["summary"]
  cell = f"{s['rendering_parts']} of {s['pairs']}, {s['slot_roles']['rendering'][1][0]:.2f}"
  return cell, [name]


def room_slot_routing() -> list[str]:
  """docs/rooms.md: where each stage puts the chairs of the source view, slot by slot."""
  rows = ["| run | step | pairs parted by attention / rendering / both | parted by attention, "
          "merged by the rendering | chairs rendered in their attention slot | chairs' pixels "
          "per slot 0–4, attention | the same, rendering | background in slot 0, attention | "
          "rendered without lifted features: pairs parted, chairs' pixels in slot 0 |",
          "|---|---|---|---|---|---|---|---|---|"]
  names, records = [], []
  for label, run in ROOM_SLOT_ROUTING:
    name = f"{run}.json"
    d = _val_record(name)
    s = d["summary"]
    att, ren = s["slot_roles"]["attention"], s["slot_roles"]["rendering"]  # [background, objects]
    dropped, dropped_names = _dropped_cell(run, d)
    rows.append(
        f"| {label} | {d['step']} | {s['attention_parts']} / {s['rendering_parts']} / "
        f"{s['both_part']} of {s['pairs']} | {s['attention_parts_rendering_merges']} "
        f"({s['merged_into_one_of_theirs']} into one of theirs) | "
        f"{s['rendered_slot_is_attention_slot']} of {s['objects']} | "
        + " / ".join(f"{x:.2f}" for x in att[1]) + " | "
        + " / ".join(f"{x:.2f}" for x in ren[1]) + f" | {att[0][0]:.2f} | "
        + dropped + " |")
    names += [name] + dropped_names
    records.append(d)
  return rows + ["", "Split: validation, the first 100 scenes; each run's checkpoint at the step "
                 "named, its trained parameters (the runs are at different steps: compare the slots' "
                 "roles, not the levels). A pair: two chairs of one source view, each with ≥ 20 "
                 "pixels; a stage parts it when the chairs' majority slots differ. Slots are "
                 "indexed by slot attention's learned queries (docs/method.md §1.2), so an index "
                 "keeps its role from scene to scene. The last column renders the same view with "
                 "every ray's lifted features zeroed, as training renders its masked rays "
                 "(`--lifted=dropped`; –: not computed). Computed on "
                 f"{_hosts(records)}.", tc.files_line(names)]


# (label, file): RESULTS/<file>.json from `python experiments/depth_placement.py --workdir=DIR
# --out=...` (the best checkpoint's moving average on 100 scenes, or with --checkpoint=STEP
# --params=trained --scenes=30 a step of the run's history; each row names which).
ROOM_DEPTH_PLACEMENT = (
    ("chairs, 128 px, slot noise to step 50 000 (seed 5, AMD host)",
     "room_depth_placement_chairs_128px_noise50k_seed5_amd_step50000"),
    ("the same run", "room_depth_placement_chairs_128px_noise50k_seed5_amd_step4000"),
    ("the same run to step 20 000, then the locality constraint to step 50 000",
     "room_depth_placement_chairs_128px_noise50k_loc50k_seed5_amd_step28000"),
    ("the same, s_σ starting at 0 (the paper's value)",
     "room_depth_placement_chairs_128px_noise50k_dens0_seed5_amd_step4000"),
    ("the same, s_σ starting at 0",
     "room_depth_placement_chairs_128px_noise50k_dens0_seed5_amd_step20000"),
    ("the run to step 28 000 with the locality constraint, then without the masking floor",
     "room_depth_placement_chairs_128px_noise50k_nomaskfrom28k_seed5_amd_step32000"),
)


def room_depth_placement() -> list[str]:
  """docs/rooms.md: how opaque the rendering is and where the novel views put what the source view
  sees, against the true depth."""
  rows = ["| run | checkpoint | s_σ | opacity, source view: background / chairs | depth bias, "
          "source view: background / chairs | opacity, novel views' seen pixels: background / "
          "chairs | displacement in the source view (px): background / chairs | PSNR (dB) of the "
          "seen pixels: background / chairs | NV-ARI: seen / unseen pixels | NV-ARI of the seen "
          "pixels, the source view's split carried by the true depth |",
          "|---|---|---|---|---|---|---|---|---|---|"]
  names, records = [], []
  for label, file in ROOM_DEPTH_PLACEMENT:
    name = f"{file}.json"
    d = _val_record(name)
    keys = [f"{k}_{r}" for k in ("opacity_source", "depth_bias_source") for r in ("bg", "fg")]
    keys += [f"{k}_{r}" for k in ("opacity", "displacement_px", "psnr")
             for r in ("seen_bg", "seen_fg")]
    keys += ["nv_ari_seen", "nv_ari_unseen", "nv_ari_seen_transported"]
    m = _metrics(d, name, keys, field="means")
    if "log_density_scale" not in d:
      raise tc.TableError(f"experiments/results/{name}: no log_density_scale")
    def pair(key, fmt, bg="_seen_bg", fg="_seen_fg"):
      return f"{m[key + bg]:{fmt}} / {m[key + fg]:{fmt}}"
    rows.append(f"| {label} | step {d['step']}, {d['parameters']}, {d['scenes']} scenes | "
                f"{d['log_density_scale']:.2f} | "
                f"{pair('opacity_source', '.2f', '_bg', '_fg')} | "
                f"{pair('depth_bias_source', '+.2f', '_bg', '_fg')} | {pair('opacity', '.2f')} | "
                f"{pair('displacement_px', '.1f')} | {pair('psnr', '.1f')} | "
                f"{m['nv_ari_seen']:.3f} / {m['nv_ari_unseen']:.3f} | "
                f"{m['nv_ari_seen_transported']:.3f} |")
    names.append(name)
    records.append(d)
  return rows + ["", "Split: validation, its first scenes (as many as the row says), every "
                 "view; the checkpoint named, its moving average of the parameters or its trained "
                 "ones. s_σ: the learned log scale of the density (docs/method.md §1.4), "
                 "which the scene recipe starts at −3 and the paper at 0. Opacity: Σ w along a "
                 "ray (docs/method.md §1.5), the "
                 "mean over the region's pixels. Depth bias: the median of (z − z_true) / z_true "
                 "over the region, z the camera depth the model renders (the remainder 1 − Σ w "
                 "of a ray goes to the far plane); > 0: too deep. Seen: the novel views' pixels "
                 "whose true surface point the source view sees (slotlifter_jax/regions.py); "
                 "background / chairs by the true masks. Displacement: the median distance "
                 "between where the model's and the true surface point project into the source "
                 "view. Medians and means are a scene's, then averaged over the scenes. The last "
                 "column gives every seen pixel the source view's rendered label at its true "
                 "point's projection: what NV-ARI on those pixels would read were the source "
                 f"view's split placed at the right depth. Computed on {_hosts(records)}.",
                 tc.files_line(names)]


TABLES = {"room_val100": room_val100, "room_curves": room_curves,
          "room_slot_routing": room_slot_routing, "room_depth_placement": room_depth_placement}
