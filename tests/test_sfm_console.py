"""COLMAP's INFO log stays off the console; its warnings, errors and our progress show."""

from __future__ import annotations

import os

import pycolmap

from nerfbot.sfm.console import drop_info_records, quiet_colmap

LOG = (b"I20261208 04:45:12.613309 140203083533184 bundle_adjustment.cc:46] === Global BA ===\n"
       b"I20261208 04:45:12.690566 140203083533184 bundle_adjustment_ceres.cc:1167] Bundle "
       b"adjustment report\n"
       b"    Residuals : 4314\n"
       b"\n"
       b"  Termination : CONVERGENCE\n"
       b"W20261208 04:45:13.000001 140203083533184 mapper.cc:12] few matches\n"
       b"    for image 3\n"
       b"\x1b[0;31mE20261208 04:45:13.000002 140203083533184 mapper.cc:51] Need a frame.\n"
       b"\x1b[mWARNING nerfbot.sfm: ours\n"
       b"I20261208 04:45:14.000003 140203083533184 timer.cc:90] Elapsed time: 0.001\n"
       b"sfm: features: 100%|##########| 3/3\n")


def test_info_records_and_their_report_lines_are_dropped_the_rest_kept():
    assert drop_info_records(LOG) == (
        b"W20261208 04:45:13.000001 140203083533184 mapper.cc:12] few matches\n"
        b"    for image 3\n"
        b"\x1b[0;31mE20261208 04:45:13.000002 140203083533184 mapper.cc:51] Need a frame.\n"
        b"\x1b[mWARNING nerfbot.sfm: ours\n"
        b"sfm: features: 100%|##########| 3/3\n")
    assert drop_info_records(b"") == b""
    assert drop_info_records(b"plain text, no newline") == b"plain text, no newline"


def test_a_colmap_call_shows_its_error_and_not_its_info(capfd):
    with quiet_colmap() as console:
        console.write("progress shows at once\n")
        # bundle adjustment of an empty model logs an INFO heading and an error
        pycolmap.bundle_adjustment(pycolmap.Reconstruction(), pycolmap.BundleAdjustmentOptions())
        os.write(2, b"text of ours on stderr\n")
    err = capfd.readouterr().err
    assert "progress shows at once" in err
    assert "Need at least one registered frame" in err
    assert "text of ours on stderr" in err
    assert "Global bundle adjustment" not in err
    # stderr is itself again afterwards
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"
