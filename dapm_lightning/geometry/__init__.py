"""Pure tensor geometry of DAPM: pose conventions, Ideal Ground Depth, log depth codec, bins."""

from dapm_lightning.geometry.bins import bin_centers, quantize
from dapm_lightning.geometry.camera import camera_rays, intrinsics_matrix, pixel_offsets
from dapm_lightning.geometry.constants import (
    MAX_DEPTH_M,
    MIN_DEPTH_M,
    POSE_FIELDS,
    POSE_KEYS,
    POSE_RANGES,
    POSE_UNITS,
    SKY_GREY,
    SKY_PROBABILITY_THRESHOLD,
    pose_field,
)
from dapm_lightning.geometry.depth_codec import (
    decode_log_depth,
    depth_to_grey,
    encode_log_depth,
    grey_to_depth,
    log_depth_grey,
    norm_to_grey,
    sky_at_limit,
)
from dapm_lightning.geometry.igd import DepthKind, IGDModel, IGDSpec, ideal_ground_depth
from dapm_lightning.geometry.image import unit_image
from dapm_lightning.geometry.pointcloud import camera_to_world, depth_to_points, valid_points
from dapm_lightning.geometry.pose import denormalize_pose, flip_pose, normalize_pose

__all__ = [
    "DepthKind", "IGDModel", "MAX_DEPTH_M", "POSE_FIELDS", "POSE_KEYS", "POSE_RANGES", "POSE_UNITS", "SKY_GREY",
    "SKY_PROBABILITY_THRESHOLD", "pose_field", "sky_at_limit", "unit_image",
    "bin_centers", "camera_rays", "camera_to_world", "decode_log_depth", "denormalize_pose", "depth_to_grey",
    "depth_to_points",
    "encode_log_depth", "flip_pose", "grey_to_depth", "ideal_ground_depth", "intrinsics_matrix", "IGDSpec",
    "log_depth_grey", "MIN_DEPTH_M", "norm_to_grey",
    "normalize_pose", "pixel_offsets", "quantize", "valid_points",
]
