"""Readers and writers at the system's edges: calibration formats, frame sources, PLY."""

from edgerecon.io.calibration import (
    check_image_sizes,
    detect_calibration_format,
    load_rig,
    read_colmap_text,
    read_middlebury_par,
    read_opencv_camera_xml,
    read_opencv_xml_rig,
    read_openmvg_sfm_data,
    read_rig_json,
    save_rig,
    write_colmap_text,
)
from edgerecon.io.dataset import Dataset, open_dataset, write_dataset_descriptor
from edgerecon.io.frames import (
    FrameSource,
    FrameSpec,
    ImageFolderFrameSource,
    VideoFrameSource,
    open_frame_source,
    probe_image_size,
    probe_video,
)
from edgerecon.io.ply import atomic_write_bytes, atomic_write_text, read_ply, write_ply

__all__ = [
    "Dataset",
    "FrameSource",
    "FrameSpec",
    "ImageFolderFrameSource",
    "VideoFrameSource",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_image_sizes",
    "detect_calibration_format",
    "load_rig",
    "open_dataset",
    "open_frame_source",
    "probe_image_size",
    "probe_video",
    "read_colmap_text",
    "read_middlebury_par",
    "read_opencv_camera_xml",
    "read_opencv_xml_rig",
    "read_openmvg_sfm_data",
    "read_ply",
    "read_rig_json",
    "save_rig",
    "write_colmap_text",
    "write_dataset_descriptor",
    "write_ply",
]
