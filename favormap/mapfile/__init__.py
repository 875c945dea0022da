"""mapfile: the persistent HDF5 map (schema in schemas/), atomic writer, lazy reader."""

from .layout import describe_layout
from .model import MapData, new_landmark_ids
from .reader import Map
from .schema import FORMAT, FORMAT_VERSION, POSE_CONVENTION, check_file, load_schema
from .writer import MapWriter, atomic_path, write_map

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "Map",
    "MapData",
    "MapWriter",
    "POSE_CONVENTION",
    "atomic_path",
    "check_file",
    "describe_layout",
    "load_schema",
    "new_landmark_ids",
    "write_map",
]
