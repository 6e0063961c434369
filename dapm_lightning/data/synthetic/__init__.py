"""Synthetic UAPD-format data: ray-cast worlds of several scene families seen by the exact camera (docs/conventions.md).

Scenes (:mod:`.scene`) are dense downtowns, suburbs, industrial estates (:mod:`.urban`), farmland,
forest (:mod:`.rural`) and water (coast, lake, river: :mod:`.water`), with vehicles and people at their
real size (:mod:`.objects`), on a ground plane that reaches the horizon. Embree (:mod:`.engine`) casts
the rays against their triangle meshes; the ground is intersected analytically, so its depth is exactly
the ideal ground depth. :mod:`.shading` gives materials, sun and cast shadows, haze, clouds and camera
processing. The written depth is the *range* to the hit, log-encoded to 8 bits (docs/conventions.md, "Depth encoding");
:mod:`.generate` writes data sets, byte-identical for a seed whatever the worker count or sharding.
See docs/synthetic.md.
"""

from dapm_lightning.data.synthetic.generate import (
    GENERATOR_VERSION,
    SynthFolderError,
    generate_uapd,
    image_seed,
    is_cache,
    is_current,
    render_sample,
    sample_pose,
    settings,
    settings_changes,
    shard_range,
    uapd_name,
)
from dapm_lightning.data.synthetic.render import render_scene
from dapm_lightning.data.synthetic.scene import (
    BUILDING,
    CLASS_NAMES,
    FAMILIES,
    GROUND,
    PERSON,
    SKY,
    TREE,
    VEHICLE,
    WATER,
    Scene,
    normalize_families,
    sample_scene,
)

__all__ = ["BUILDING", "CLASS_NAMES", "FAMILIES", "GENERATOR_VERSION", "GROUND", "PERSON", "SKY", "TREE", "VEHICLE",
           "WATER", "Scene", "SynthFolderError", "generate_uapd", "image_seed", "is_cache", "is_current",
           "normalize_families", "render_sample", "settings_changes",
           "render_scene", "sample_pose", "sample_scene", "settings", "shard_range", "uapd_name"]
