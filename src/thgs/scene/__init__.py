"""Scenes on disk and in memory: Gaussians, cameras (with lens distortion), and their file
formats: INRIA PLY, gsplat checkpoints, COLMAP, transforms.json, cameras.json."""

from thgs.scene.cameras import Cameras
from thgs.scene.cameras_json import read_cameras_json, write_cameras_json
from thgs.scene.colmap import read_colmap, write_colmap
from thgs.scene.distortion import Distortion
from thgs.scene.gaussians import SH_C0, Gaussians
from thgs.scene.gsplat_checkpoint import read_gsplat_checkpoint
from thgs.scene.images import find_images, fit_to_images
from thgs.scene.loader import Scene, load_cameras, load_scene
from thgs.scene.ply import read_ply, write_ply
from thgs.scene.summary import CameraSummary, SceneSummary, summarize
from thgs.scene.transforms_json import read_transforms_json, write_transforms_json

__all__ = [
    "SH_C0",
    "CameraSummary",
    "Cameras",
    "Distortion",
    "Gaussians",
    "Scene",
    "SceneSummary",
    "find_images",
    "fit_to_images",
    "load_cameras",
    "load_scene",
    "read_cameras_json",
    "read_colmap",
    "read_gsplat_checkpoint",
    "read_ply",
    "read_transforms_json",
    "summarize",
    "write_cameras_json",
    "write_colmap",
    "write_ply",
    "write_transforms_json",
]
