"""Fitting: per scan and per position (two faces together), batch, joint across scans,
streamed, Dask; north alignment; fit.json and the residual tables."""

from ._align import Alignment, north_alignment
from ._fit import CampaignFit, fit_campaign, fit_json, fit_scan, read_residuals, ScanFit, write_fit
from ._joint import fit_joint, JointFit, write_joint_fit
from ._stream import stream_fit_campaign, stream_fit_scan
from ._distributed import fit_dask

__all__ = [
    "Alignment",
    "CampaignFit",
    "fit_campaign",
    "fit_dask",
    "fit_joint",
    "fit_json",
    "fit_scan",
    "JointFit",
    "north_alignment",
    "read_residuals",
    "ScanFit",
    "stream_fit_campaign",
    "stream_fit_scan",
    "write_fit",
    "write_joint_fit",
]
