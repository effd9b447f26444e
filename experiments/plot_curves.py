"""Learning curves of a run: `python experiments/plot_curves.py RUN_DIR|METRICS.jsonl [OUT.png]`.

Reads RUN_DIR/metrics.jsonl (written by training), or a copied metrics file and draws train loss/PSNR with the schedules
(keep ratio, slot noise, locality) and the validation PSNR / ARI / FG-ARI / NV-ARI over steps.
Default output: RUN_DIR/curves.png.
"""

import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_metrics(run_dir: str) -> tuple[list[dict], list[dict]]:
  train, val = [], []
  path = run_dir if os.path.isfile(run_dir) else os.path.join(run_dir, "metrics.jsonl")
  with open(path) as f:
    for line in f:
      row = json.loads(line)
      (train if row["kind"] == "train" else val).append(row)
  return train, val


def plot(run_dir: str, out: str) -> None:
  train, val = read_metrics(run_dir)
  fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
  steps = [r["step"] for r in train]
  axes[0].plot(steps, [r["psnr"] for r in train], lw=0.8, label="train PSNR (batch)")
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
    axes[2].plot(steps, [r[key] for r in train], label=key)
  ax = axes[2].twinx()
  ax.plot(steps, [r["lr_backbone"] for r in train], "k--", lw=0.8, label="lr backbone")
  ax.set_ylabel("lr")
  axes[2].set_xlabel("step")
  axes[2].set_title("schedules")
  axes[2].legend(fontsize=8, loc="center right")
  fig.tight_layout()
  fig.savefig(out, dpi=80)
  print(f"wrote {out}")


if __name__ == "__main__":
  run = sys.argv[1]
  default = os.path.splitext(run)[0] + ".png" if os.path.isfile(run) else os.path.join(run, "curves.png")
  plot(run, sys.argv[2] if len(sys.argv) > 2 else default)
