"""The embedded default data set: procedural scenes, analytic ray caster (docs/method.md §3.5).

This module is only the generator's one import name: callers (the CLI `data.generate`, the data
cache `embedded.py`, the experiments and the tests) keep writing `generator.X` while the code lives
in modules split by concern, each importing only those before it:

  layout     scenes and cameras: constants, SceneSpec and its parts, CLEVR and room layouts,
             object options (NumPy only, no JAX)
  raycaster  a scene packed into arrays, ray–primitive intersection, trace, surface normals (JAX)
  shading    textures, lights, shadows, mirror bounce, camera rays and the staged render of views
  writer     one scene (sample until visible, render) and the uORF folder writer

Camera math shared with the data readers (uORF intrinsics, look-at poses) is in `cameras.py`.
"""

from slotlifter_jax.data.cameras import look_at_cam_to_world
from slotlifter_jax.data.layout import (
    BACKGROUND_LABEL, CAMERA_ELEVATION_DEG, CAMERA_ELEVATION_JITTER_DEG, CAMERA_RADIUS,
    CAMERA_RADIUS_JITTER, CHAIR_PARTS, CLEVR_COLOURS, CLEVR_FOOTPRINT, CLEVR_MATERIALS,
    CLEVR_MAX_BOUNDING_RADIUS, CLEVR_NUM_OBJECTS, CLEVR_SHAPES, CLEVR_SIZES, CLEVR_XY_RANGE,
    FAMILIES, FOCAL_X_PER_WIDTH, FOCAL_Y_PER_HEIGHT, GENERATOR_VERSION, LABEL_GREY_STEP,
    MAX_LAYOUT_DRAWS, MAX_OBJECT_SCALE, MAX_OBJECTS, MIN_GAP, MIN_VISIBLE_PIXELS_128,
    PRIMITIVE_KINDS, ROOM_HALF_SIZE, ROOM_NUM_CHAIRS, ROOM_OBJECTS, ROOM_TEXTURES, ROOM_XY_RANGE, SCENE_SCALE,
    SPLIT_STREAMS, SPLITS, SUBSETS, WOOD_COLOURS, CameraSpec, Light, Material, ObjectOptionError, Primitive,
    SceneObject, SceneSpec, camera_to_world, check_object_options, is_default_objects,
    label_grey_levels, min_visible_pixels, normalised_intrinsics, num_source_views_for,
    object_count_range, sample_cameras, sample_clevr_layout, sample_room_layout, uorf_intrinsics)
from slotlifter_jax.data.raycaster import (
    DIR_EPS, FLOOR, GAMMA, NUM_BACKGROUND_SURFACES, QUAD_EPS, T_MIN, TEX_CHECKER, TEX_NOISE,
    TEX_PLAIN, TEX_STRIPES, TEX_TILES, TEX_WOOD, TEXTURE_IDS, UNBOUNDED, WALLS, Hit, RenderOptions,
    SceneArrays, Vec, intersect_primitives, render_options, scene_arrays, surface_normals, trace)
from slotlifter_jax.data.shading import (SKY_LINEAR, SURFACE_OFFSET, Render, camera_rays,
                                         render_centre, render_views, shade, value_noise)
from slotlifter_jax.data.writer import (PNG_COMPRESS_LEVEL, GeneratedScene, _split_header,
                                        generate_dataset, generate_scene, mask_to_grey_rgb,
                                        scene_rng, view_stem)
