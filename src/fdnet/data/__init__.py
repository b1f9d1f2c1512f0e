"""Datasets (one folder per condition, VPR-Bench layouts), images, ground truth, filters."""

from fdnet.data.dataset import RouteDataset, Traverse, parse_frame_range
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images, load_image, load_images

__all__ = [
    "RouteDataset",
    "Traverse",
    "GroundTruth",
    "parse_frame_range",
    "list_images",
    "load_image",
    "load_images",
]
