"""RGBN images (colour + normals): the data type, its storage, and processing (§7.2)."""

from common.rgbn.image import RGBNImage, load_rgbn, read_rgbn, save_rgbn, write_rgbn

__all__ = ["RGBNImage", "load_rgbn", "read_rgbn", "save_rgbn", "write_rgbn"]
