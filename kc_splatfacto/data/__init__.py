"""Data layer: dataparsers (SPARS3R, COLMAP, transforms.json, demo) -> DataparserOutputs; datasets of uint8 images."""

from kc_splatfacto.data.base import (
    DataParser,
    DataParserConfig,
    DataParserError,
    PoseNormalization,
    read_dataparser_transforms,
    write_dataparser_transforms,
)
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.detect import detect_format, resolve_dataparser
from kc_splatfacto.data.outputs import Cameras, DataparserOutputs

__all__ = [
    "Cameras",
    "DataParser",
    "DataParserConfig",
    "DataParserError",
    "DataparserOutputs",
    "ImageDataset",
    "PoseNormalization",
    "detect_format",
    "read_dataparser_transforms",
    "resolve_dataparser",
    "write_dataparser_transforms",
]
