"""Learning curves of a run.

  python -m slotlifter_jax.tools.plot_curves RUN_DIR|METRICS.jsonl [OUT.png]

Reads RUN_DIR/metrics.jsonl (written by training), or a copied metrics file and draws train loss/PSNR with the schedules
(keep ratio, slot noise, locality) and the validation PSNR / ARI / FG-ARI / NV-ARI over steps.
A second row shows the emergence of objects: slot attention FG-ARI, FG-ARI and NV-ARI against steps
and against minutes of wall time, with the time to decomposition (FG-ARI ≥ 0.5 and ≥ 0.8) marked
and printed (slotlifter_jax/emergence.py defines both; logs without `wall_s` count wall time from
their first record's timestamp). Default output: RUN_DIR/curves.png.
"""

import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from slotlifter_jax import emergence  # noqa: E402  (numpy and absl only, no JAX)

EMERGENCE_KEYS = ("attn_fg_ari", "fg_ari", "nv_ari")


def _records(run_dir: str) -> list[dict]:
  path = run_dir if os.path.isfile(run_dir) else os.path.join(run_dir, emergence.METRICS_FILE)
  return emergence.load_records(path)


def _split(records: list[dict]) -> tuple[list[dict], list[dict]]:
  latest = emergence.latest_records(records)
  return [r for r in latest if r["kind"] == "train"], [r for r in latest if r["kind"] == "val"]


TABLE = (("keep ratio", "keep_ratio", "{:.2f}"), ("novel PSNR", "psnr_novel", "{:.1f}"),
         ("attn_fg_ari", "attn_fg_ari", "{:.3f}"), ("FG-ARI", "fg_ari", "{:.3f}"),
         ("FG-ARI ≥ 2 obj", "fg_ari_multi", "{:.3f}"), ("NV-ARI", "nv_ari", "{:.3f}"), ("active slots", "active_slots", "{:.2f}"),
         ("largest share", "probe_largest_share", "{:.2f}"))


def validation_table(records: list[dict]) -> list[str]:
  """The validations as a markdown table (the README's tables), with the keep ratio of the
  schedule at that step."""
  train, val = _split(records)
  keep = {r["step"]: r.get("keep_ratio") for r in train}
  c = emergence.curves(records, [key for _, key, _ in TABLE if key != "keep_ratio"])
  lines = ["| step | wall min | " + " | ".join(name for name, _, _ in TABLE) + " |",
           "|---" * (len(TABLE) + 2) + "|"]
  for i, step in enumerate(c["step"]):
    nearest = min(keep, key=lambda s: abs(s - step)) if keep else None
    values = {key: c[key][i] for _, key, _ in TABLE if key != "keep_ratio"}
    values["keep_ratio"] = keep.get(nearest)
    cells = ["–" if values[key] is None or values[key] != values[key] else fmt.format(values[key])
             for _, key, fmt in TABLE]  # – : not logged (older runs) or no such view
    lines.append(f"| {int(step)} | {c['minutes'][i]:.1f} | " + " | ".join(cells) + " |")
  return lines


def read_metrics(run_dir: str) -> tuple[list[dict], list[dict]]:
  """(train, validation) records sorted by step, a resumed run's repeated steps resolved."""
  return _split(_records(run_dir))


def plot_emergence(records: list[dict], ax_step, ax_wall, ax_text) -> list[str]:
  """The segmentation metrics against steps and wall minutes, with FG-ARI's threshold crossings.

  `records`: the whole log in file order (the fallback clock starts at its first record). Returns
  the time-to-decomposition lines it prints into `ax_text`.
  """
  curves = emergence.curves(records, keys=EMERGENCE_KEYS)
  result = emergence.time_to_decomposition(records, key="fg_ari")
  for ax, x in ((ax_step, "step"), (ax_wall, "minutes")):
    for key in EMERGENCE_KEYS:
      if curves[key].size and not all(math.isnan(v) for v in curves[key]):
        ax.plot(curves[x], curves[key], "o-", ms=3, lw=1, label=emergence.label(key))
    for t in result["thresholds"]:
      ax.axhline(t, color="grey", ls="--", lw=0.8)
      c = result["crossings"][f"{t:g}"]
      if c is not None and math.isfinite(c[x]):
        ax.axvline(c[x], color="k", ls=":", lw=0.8)
        ax.annotate(f"FG-ARI ≥ {t:g}: {c['minutes']:.1f} min\n(step {c['step']})",
                    (c[x], t), xytext=(4, -22), textcoords="offset points", fontsize=7,
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none", alpha=0.8))
    ax.set_ylim(-0.05, 1.05)
    ax.set_ylabel("ARI")
    if ax.has_data() and ax.get_legend_handles_labels()[0]:
      ax.legend(fontsize=7, loc="upper left")
  ax_step.set_xlabel("step")
  ax_step.set_title("emergence of objects (validation)")
  clock = {"wall_s": "", "none": ""}.get(result["wall_clock"], " (from record timestamps)")
  ax_wall.set_xlabel(f"wall time, minutes{clock}")
  ax_wall.set_title("emergence against wall time")
  lines = emergence.summary_lines(result)
  ax_text.axis("off")
  ax_text.text(0, 1, "\n".join(lines), va="top", fontsize=7.5, wrap=True,
               transform=ax_text.transAxes)
  return lines


def plot(run_dir: str, out: str) -> None:
  records = _records(run_dir)
  train, val = _split(records)
  fig, grid = plt.subplots(2, 3, figsize=(13, 7.2))
  axes = grid[0]
  steps = [r["step"] for r in train]
  axes[0].plot(steps, [r.get("psnr", float("nan")) for r in train], lw=0.8,
               label="train PSNR (batch)")
  if val:
    axes[0].plot([r["step"] for r in val], [r.get("psnr_novel", float("nan")) for r in val], "o-",
                 label="val novel-view PSNR")
  axes[0].set_xlabel("step")
  axes[0].set_ylabel("dB")
  axes[0].legend(fontsize=8)
  for key in ("ari", "fg_ari", "nv_ari", "nv_fg_ari", "attn_fg_ari"):
    if val and key in val[0]:
      axes[1].plot([r["step"] for r in val], [r.get(key, float("nan")) for r in val], "o-",
                   label="slot attention 2D FG-ARI" if key == "attn_fg_ari" else key)
  axes[1].set_xlabel("step")
  axes[1].set_title("validation segmentation")
  axes[1].legend(fontsize=8)
  for key in ("keep_ratio", "slot_noise_sigma", "locality"):
    axes[2].plot(steps, [r.get(key, float("nan")) for r in train], label=key)
  ax = axes[2].twinx()
  ax.plot(steps, [r.get("lr_backbone", float("nan")) for r in train], "k--", lw=0.8,
          label="lr backbone")
  ax.set_ylabel("lr")
  axes[2].set_xlabel("step")
  axes[2].set_title("schedules")
  axes[2].legend(fontsize=8, loc="center right")
  lines = plot_emergence(records, *grid[1])
  fig.tight_layout()
  fig.savefig(out, dpi=80)
  print("\n".join(lines + [""] + validation_table(records)))
  print(f"wrote {out}")


def main(argv: list[str]) -> None:
  if len(argv) > 1 and argv[1] in ("-h", "--help"):
    print(__doc__)
    return
  if len(argv) not in (2, 3):
    sys.exit(f"usage: {__doc__.split(chr(10) * 2)[1].strip()}")
  run = argv[1]
  if not os.path.isfile(run) and not os.path.isfile(os.path.join(run, emergence.METRICS_FILE)):
    sys.exit(f"error: {run}: neither a metrics .jsonl file nor a run folder with "
             f"{emergence.METRICS_FILE}")
  default = os.path.splitext(run)[0] + ".png" if os.path.isfile(run) else os.path.join(run, "curves.png")
  plot(run, argv[2] if len(argv) > 2 else default)


if __name__ == "__main__":
  main(sys.argv)
