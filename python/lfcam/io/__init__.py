"""Files in and out: images and raw captures (camera raw files through the ``raw``
extra, with their metadata), PFM and ``.flo`` arrays, PLY, atomic writing, display
encodings and checksums. The only subpackage that opens files (the
calibration file's HDF5 layout lives with the :class:`~lfcam.Calibration` type)."""

from .atomic import atomic_folder, atomic_output, write_text_atomic
from .checksum import file_hash
from .display import colour_depth, encode_u8, encode_u16, rgb_u8, srgb_decode, srgb_encode
from .files import read_file_bytes
from .formats import read_flo, read_pfm, write_pfm
from .images import (
    BAYER_PATTERNS,
    IMAGE_EXTENSIONS,
    MAX_IMAGE_FILE_BYTES,
    MAX_IMAGE_PIXELS,
    MAX_IMAGE_SIDE,
    demosaic,
    is_image_file,
    read_image,
    read_raw,
    read_tiff_description,
    to_float,
    write_image,
    write_image_atomic,
)
from .ply import write_ply
from .raw import RAW_EXTENSIONS, CaptureMetadata, is_camera_raw, read_metadata, write_dng

__all__ = [
    "BAYER_PATTERNS",
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_FILE_BYTES",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE",
    "RAW_EXTENSIONS",
    "CaptureMetadata",
    "atomic_folder",
    "atomic_output",
    "colour_depth",
    "demosaic",
    "encode_u8",
    "encode_u16",
    "file_hash",
    "is_camera_raw",
    "is_image_file",
    "read_file_bytes",
    "read_flo",
    "read_image",
    "read_metadata",
    "read_pfm",
    "read_raw",
    "read_tiff_description",
    "rgb_u8",
    "srgb_decode",
    "srgb_encode",
    "to_float",
    "write_dng",
    "write_image",
    "write_image_atomic",
    "write_pfm",
    "write_ply",
    "write_text_atomic",
]
