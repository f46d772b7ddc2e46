"""Scene loading for the renderer (kept for existing callers): the implementation lives
in :mod:`ppmrecon.scene` (loader, Mitsuba 0.6 import, one module per plugin kind)."""

from ..scene.common import SceneError, describe, ensure_variant, mitsuba_error_line, one_line
from ..scene.loader import (DEFAULT_SCENE, SCENES_DIR, SUPPORTED_EMITTERS, SUPPORTED_SENSORS, LoadedScene,
                            apply_resolution, builtin_scenes, check_files, load_scene, load_tree,
                            parse_version, refuse_unsupported, take_integrator)

__all__ = ["SceneError", "describe", "ensure_variant", "mitsuba_error_line", "one_line", "DEFAULT_SCENE",
           "SCENES_DIR", "SUPPORTED_EMITTERS", "SUPPORTED_SENSORS", "LoadedScene", "apply_resolution",
           "builtin_scenes", "check_files", "load_scene", "load_tree", "parse_version", "refuse_unsupported",
           "take_integrator"]
