"""Real-world datasets (file formats, loaders, validation)."""

from resloc.datasets.mrclam import MRCLAMDataset, RobotLog, load_mrclam

__all__ = ["MRCLAMDataset", "RobotLog", "load_mrclam"]
