"""Rendering with a trained model, from single rays to the pictures of `--mode=render`.

  volume.py    volume rendering of colour, depth and per-slot segmentation along rays (pure
               functions on any leading shape, docs/method.md §1.5)
  views.py     chunked full-view rendering of a scene's cameras (`SceneRenderer`, `RenderedViews`)
  adaptive.py  adaptive full-view rendering (`render.adaptive`): windows of the sample
               grid placed by a sparse proposal pass; `make_scene_renderer` picks it or views.py
  pictures.py  the `--mode=render` pictures: per-scene panels with per-slot renderings, orbit GIFs

No re-exports: import the module you need, e.g. `from slotlifter_jax.rendering import volume`.
"""
