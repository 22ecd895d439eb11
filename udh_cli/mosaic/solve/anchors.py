"""What anchors a run's global solve: ground-control observations, GPS fixes, or both."""

from __future__ import annotations

from udh_cli.mosaic.georef.anchors import Anchors
from udh_cli.mosaic.georef.gcp import GcpFile, gcp_anchors
from udh_cli.mosaic.inputs.frames import FrameSet, gps_fixes
from udh_cli.mosaic.pairs.gps import ground_positions
from udh_cli.mosaic.report import Reporter


def solve_anchors(frameset: FrameSet, gcp_sigma_m: float, gps_sigma_m: float, reporter: Reporter, gcps: GcpFile | None = None,
                  gcp_image_width: int | None = None, leave_out: str | None = None) -> Anchors | None:
    """The anchors of the global solve: ground-control observations (``gcp_sigma_m``, metres), GPS fixes
    (``gps_sigma_m``, metres; 0: off), or both when they share a CRS; None for none. ``leave_out``: a ground-control
    point to leave out (checking it honestly)."""
    sizes = [f.size for f in frameset.frames]
    found = None
    if gcp_sigma_m > 0 and gcps is None:
        reporter.warn(f"--gcp-sigma {gcp_sigma_m}: no ground-control file (--gcp); the solve does without it")
    if gcp_sigma_m > 0 and gcps is not None:
        frames = {f.name: (f.index, f.size) for f in frameset.frames}
        found = gcp_anchors(gcps, frames, gcp_sigma_m, gcp_image_width, leave_out)
    if gps_sigma_m > 0:
        fixes = gps_fixes(frameset.frames)
        if not fixes:
            reporter.warn(f"--gps-sigma {gps_sigma_m}: no frame carries GPS; the solve does without it")
        else:
            epsg, positions = ground_positions(fixes)
            gps = Anchors.frame_centres(positions, sizes, gps_sigma_m)
            if found is not None and epsg != gcps.epsg:
                reporter.warn(f"--gps-sigma: the GPS fixes are in EPSG:{epsg}, the ground-control points in EPSG:{gcps.epsg}; "
                              "the solve is anchored by the ground-control points alone")
            else:
                found = gps if found is None else found + gps
    return found
