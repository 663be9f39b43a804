"""Campaign I/O: ``campaign.toml`` and its scan tables (Parquet, E57), readers of PTX/XYZ/E57
exports with telescope presets, validation, crash-safe output, the observing schedule."""

from ._campaign import default_campaign, iter_scan_chunks, load_campaign, read_scan, write_campaign
from ._format import (
    Campaign,
    CampaignError,
    ScanData,
    ScanMeta,
    Scanner,
    Site,
    Telescope,
    cartesian_to_raw,
    minimum_points,
    require_points,
)
from ._import import import_file, read_ptx, read_xyz, telescope_preset
from ._safeio import OutputDir, verify_result_dir, write_json_atomic
from ._schedule import campaign_plan, plan_positions

__all__ = [
    "Campaign",
    "campaign_plan",
    "CampaignError",
    "cartesian_to_raw",
    "default_campaign",
    "import_file",
    "iter_scan_chunks",
    "load_campaign",
    "minimum_points",
    "OutputDir",
    "plan_positions",
    "read_ptx",
    "read_scan",
    "read_xyz",
    "require_points",
    "ScanData",
    "ScanMeta",
    "Scanner",
    "Site",
    "Telescope",
    "telescope_preset",
    "verify_result_dir",
    "write_campaign",
    "write_json_atomic",
]
