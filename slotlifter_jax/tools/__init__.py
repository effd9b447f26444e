"""Command-line tools that read, compare and fork training runs, one module each:

  python -m slotlifter_jax.tools.plot_curves RUN_DIR|METRICS.jsonl [OUT.png]
  python -m slotlifter_jax.tools.compare_curves --run=LABEL=PATH ... --out=curves.png
  python -m slotlifter_jax.tools.metrics_table --group=NAME=FILE[,FILE...] ...
  python -m slotlifter_jax.tools.paired_eval BASE_EVAL OTHER_EVAL [OTHER_EVAL ...]
  python -m slotlifter_jax.tools.fork_run SRC DST --checkpoint=STEP
  python -m slotlifter_jax.tools.early_check --step=STEP --min_score=X RUN ...
  python -m slotlifter_jax.tools.headline --name=NAME --split=SPLIT --out=FILE.json RUN ...

Each module's docstring gives its use. Only paired_eval and headline import JAX when loaded,
through the library modules they read runs with (metrics, restarts); fork_run does inside fork().
None imports from experiments/: the studies there use these tools, not the other way round
(tests/test_imports.py).
"""
