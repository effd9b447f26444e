"""Does the rendering keep the objects apart that slot attention parted? Object by object.

  python experiments/slot_routing.py --workdir=DIR [--split=val --scenes=20 --checkpoint=best
      --params=average --lifted=kept --out=experiments/results/NAME.json]

The rendered split has two stages: slot attention groups the source view's features into K slots,
then the point-slot mapping W (docs/method.md §1.4) gives each 3D point to one of those slots.
`experiments/diagnose_slots.py` scores the first stage with an ARI; this script follows each
ground-truth object of the source view through both, with the run's own config (DIR/config.json):

  attention slot   the slot that slot attention gives most of the object's pixels (argmax of the
                   last iteration, each pixel taking its feature cell's, metrics.attention_labels)
  rendered slot    the slot that owns most of the object's pixels in the source view rendered from
                   that same source view (argmax over K of the rendered segmentation)

and counts, over the pairs of objects in one view, how often each stage parts them (gives them
different slots). A pair that attention parts and the rendering merges is the failure this looks
for: the slots are distinct and the mapping still sends both objects' points to one of them.
For those pairs it says where the merged pair went: to the slot that attention gave one of the two
(the other object's slot lost its points) or to a slot attention gave neither. It also reports the
cosine of the two objects' slots and of their mapping keys k(S') (the vectors the points' queries
are compared with), so one can see whether the mapping can tell the slots apart at all.

--lifted=dropped renders every ray as training renders a masked one (docs/method.md §1.3): its
lifted features zeroed, so what it gives a point comes from the slots and the point's position
alone. The rendered slot is then what the slots alone say about where each object is; where it
matches the default (`kept`), the lifted features play no part in the routing.

Objects with fewer than --min_pixels pixels in the source view are left out (a chair leg at the
image border carries no majority). Nothing here reads the test split unless --split says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import diagnose_slots  # noqa: E402


def majority_slots(mask: np.ndarray, labels: np.ndarray, *,
                   min_pixels: int) -> dict[int, tuple[int, float]]:
  """Each foreground object of `mask` [H, W] (0 = background) with ≥ min_pixels pixels →
  (the slot of `labels` [H, W] that most of its pixels carry, the share of its pixels that carry
  it). Ties go to the lowest slot."""
  mask, labels = np.asarray(mask), np.asarray(labels)
  if mask.shape != labels.shape:
    raise ValueError(f"mask {mask.shape} and labels {labels.shape} differ in shape")
  out = {}
  for obj in np.unique(mask):
    if obj == 0:
      continue
    slots = labels[mask == obj]
    if slots.size < min_pixels:
      continue
    counts = np.bincount(slots.astype(np.int64))
    out[int(obj)] = (int(counts.argmax()), float(counts.max() / slots.size))
  return out


def pair_outcomes(attention: dict[int, tuple[int, float]],
                  rendered: dict[int, tuple[int, float]]) -> list[dict]:
  """Every pair of objects present in both maps → which stage parts it, and for a pair attention
  parts and the rendering merges, whether the merged slot is one of the pair's attention slots."""
  objs = sorted(set(attention) & set(rendered))
  rows = []
  for i, a in enumerate(objs):
    for b in objs[i + 1:]:
      att_a, att_b = attention[a][0], attention[b][0]
      ren_a, ren_b = rendered[a][0], rendered[b][0]
      row = dict(objects=(a, b), attention_parts=att_a != att_b, rendering_parts=ren_a != ren_b,
                 attention_slots=(att_a, att_b), rendered_slots=(ren_a, ren_b))
      if row["attention_parts"] and not row["rendering_parts"]:
        row["merged_into"] = "one of theirs" if ren_a in (att_a, att_b) else "another slot"
      rows.append(row)
  return rows


def summarise(pairs: list[dict], objects: list[dict]) -> dict:
  """Counts over all pairs and objects of a split (see the module docstring)."""
  def count(pred):
    return int(sum(1 for p in pairs if pred(p)))
  parted = [p for p in pairs if p["attention_parts"]]
  merged = [p for p in parted if not p["rendering_parts"]]
  both = [p for p in parted if p["rendering_parts"]]
  mean_of = lambda rows, key: float(np.mean([r[key] for r in rows])) if rows else float("nan")
  return dict(
      pairs=len(pairs),
      attention_parts=len(parted),
      rendering_parts=count(lambda p: p["rendering_parts"]),
      both_part=len(both),
      attention_parts_rendering_merges=len(merged),
      attention_merges_rendering_parts=count(
          lambda p: not p["attention_parts"] and p["rendering_parts"]),
      merged_into_one_of_theirs=int(sum(p["merged_into"] == "one of theirs" for p in merged)),
      merged_pairs_slot_cosine=mean_of(merged, "slot_cosine"),
      merged_pairs_key_cosine=mean_of(merged, "key_cosine"),
      parted_pairs_slot_cosine=mean_of(both, "slot_cosine"),
      parted_pairs_key_cosine=mean_of(both, "key_cosine"),
      objects=len(objects),
      rendered_slot_is_attention_slot=int(sum(o["rendered"] == o["attention"] for o in objects)),
      attention_purity=mean_of(objects, "attention_share"),
      rendered_purity=mean_of(objects, "rendered_share"),
  )


def _cosine(x: np.ndarray, y: np.ndarray) -> float:
  x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
  return float(x @ y / max(np.linalg.norm(x) * np.linalg.norm(y), 1e-12))


def _rounded(x, digits: int = 4):
  """x with every float rounded: the per-pair cosines and shares need no more."""
  if isinstance(x, float):
    return round(x, digits)
  if isinstance(x, dict):
    return {k: _rounded(v, digits) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_rounded(v, digits) for v in x]
  return x


def _lines_json(record: dict) -> str:
  """JSON with the long lists (pairs, objects) one entry per line, their floats to 4 digits."""
  plain = json.loads(json.dumps(record, default=lambda x: x.item() if hasattr(x, "item") else str(x)))
  parts = []
  for key, value in plain.items():
    if isinstance(value, list) and value and isinstance(value[0], dict):
      body = ",\n".join(json.dumps(_rounded(v), separators=(",", ":")) for v in value)
      parts.append(f"{json.dumps(key)}: [\n{body}\n]")
    else:
      parts.append(f"{json.dumps(key)}: {json.dumps(value, separators=(',', ':'))}")
  return "{\n" + ",\n".join(parts) + "\n}\n"


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  diagnose_slots.add_run_arguments(p)
  p.add_argument("--params", default="average", help="average | trained")
  p.add_argument("--lifted", choices=("kept", "dropped"), default="kept",
                 help="dropped: render without the lifted features (module docstring)")
  p.add_argument("--min_pixels", type=int, default=20)
  p.add_argument("--out", default="", help="write the summary and the pairs to this JSON file")
  args = p.parse_args(argv)

  from slotlifter_jax import provenance
  from slotlifter_jax.rendering import views as views_lib

  run = diagnose_slots.load_run(args, params=args.params)
  renderer = views_lib.SceneRenderer(run.model, run.config, drop_lifted=args.lifted == "dropped")
  mapping = run.params["allocation"]["map_key"]
  pairs, objects = [], []
  k = int(run.config.model.num_slots)
  # [stage, region, slot] pixel counts: stage 0 attention, 1 rendering; region 0 background, 1 objects
  roles = np.zeros((2, 2, k), np.int64)
  for n, scene in enumerate(run.scenes):
    if scene.masks is None:
      raise SystemExit(f"{args.workdir}: split {args.split!r} has no ground-truth masks")
    source = int(np.asarray(scene.source_indices)[0])
    out = renderer.render(run.params, scene, [source])
    attention_labels = out.source_labels[0]  # [H, W]
    rendered_labels = out.segmentation[0].argmax(-1)  # [H, W]
    mask = scene.masks[source]
    for stage, labels in enumerate((attention_labels, rendered_labels)):
      for region, where in enumerate((mask == 0, mask != 0)):
        roles[stage, region] += np.bincount(labels[where].ravel(), minlength=k)[:k]
    att = majority_slots(mask, attention_labels, min_pixels=args.min_pixels)
    ren = majority_slots(mask, rendered_labels, min_pixels=args.min_pixels)
    slots = np.asarray(out.slots)  # [K, Ds]
    keys = slots @ np.asarray(mapping["kernel"]) + np.asarray(mapping["bias"])
    for obj in sorted(att):
      objects.append(dict(scene=n, object=obj, attention=att[obj][0], attention_share=att[obj][1],
                          rendered=ren[obj][0], rendered_share=ren[obj][1]))
    colour = {obj: scene.images[source][mask == obj].mean(0) for obj in att}  # mean RGB
    for row in pair_outcomes(att, ren):
      sa, sb = row["attention_slots"]
      oa, ob = row["objects"]
      row.update(scene=n, slot_cosine=_cosine(slots[sa], slots[sb]),
                 key_cosine=_cosine(keys[sa], keys[sb]),
                 key_norms=(float(np.linalg.norm(keys[sa])), float(np.linalg.norm(keys[sb]))),
                 colour_distance=float(np.linalg.norm(colour[oa] - colour[ob])))
      pairs.append(row)
  summary = summarise(pairs, objects)
  print(f"{args.workdir}: step {run.step} ({run.parameters} parameters), {len(run.scenes)} "
        f"{args.split} scenes, {summary['objects']} objects, {summary['pairs']} pairs, lifted "
        f"features {args.lifted}")
  print(f"  pairs parted by slot attention {summary['attention_parts']}, by the rendering "
        f"{summary['rendering_parts']}, by both {summary['both_part']}")
  print(f"  parted by attention, merged by the rendering: "
        f"{summary['attention_parts_rendering_merges']} (into one of their attention slots: "
        f"{summary['merged_into_one_of_theirs']}); merged by attention, parted by the rendering: "
        f"{summary['attention_merges_rendering_parts']}")
  print(f"  slot / key cosine of the two attention slots: merged pairs "
        f"{summary['merged_pairs_slot_cosine']:.3f} / {summary['merged_pairs_key_cosine']:.3f}, "
        f"pairs both part {summary['parted_pairs_slot_cosine']:.3f} / "
        f"{summary['parted_pairs_key_cosine']:.3f}")
  print(f"  objects whose rendered slot is their attention slot: "
        f"{summary['rendered_slot_is_attention_slot']} of {summary['objects']}; purity attention "
        f"{summary['attention_purity']:.2f}, rendered {summary['rendered_purity']:.2f}")
  shares = roles / np.maximum(roles.sum(-1, keepdims=True), 1)
  print("  slot roles (share of the background's / the objects' pixels each slot holds; slots as "
        "indexed by the learned queries):")
  for stage, name in enumerate(("attention", "rendering")):
    print(f"    {name:9s} " + "  ".join(f"slot {i}: {shares[stage, 0, i]:.2f} / "
                                        f"{shares[stage, 1, i]:.2f}" for i in range(k)))
  summary["slot_roles"] = dict(attention=shares[0].tolist(), rendering=shares[1].tolist())
  if args.out:
    record = dict(summary=summary, pairs=pairs, objects=objects, workdir=args.workdir,
                  split=args.split, scenes=len(run.scenes), step=int(run.step),
                  parameters=run.parameters, checkpoint=args.checkpoint,
                  min_pixels=args.min_pixels, lifted=args.lifted,
                  provenance=provenance.collect(run.config))
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
      # One line per pair and object keeps a 100-scene file small and still diffable.
      f.write(_lines_json(record))
    os.replace(tmp, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
