"""RGBN images (colour + normals): the data type, its storage, and processing (§7.2)."""

from common.rgbn.image import RGBNImage, load_rgbn, read_rgbn, save_rgbn, write_rgbn
from common.rgbn.bilateral import joint_bilateral
from common.rgbn.curvature import Curvature, curvature, mean_curvature
from common.rgbn.io import load_rgbn_files, read_albedo, read_normal_map, write_image
from common.rgbn.segmentation import segment_rgbn
from common.rgbn.smoothing import scale_space, smooth_normals, smooth_rgbn

__all__ = ["RGBNImage", "load_rgbn", "read_rgbn", "save_rgbn", "write_rgbn",
           "joint_bilateral", "Curvature", "curvature", "mean_curvature",
           "load_rgbn_files", "read_albedo", "read_normal_map", "write_image",
           "segment_rgbn", "scale_space", "smooth_normals", "smooth_rgbn"]
