"""Data layer: dataparsers (SPARS3R, COLMAP, transforms.json, demo) -> DataparserOutputs; datasets of uint8 images."""
