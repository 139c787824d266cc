"""``reach certify SOURCE --out CERT.npz`` needs no other option: each system's certification defaults,
declared beside its lemmas or derived from them (safety.formal.settings.certify_defaults)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from reach.systems import Air3D
from safety.formal.settings import CertifySettings, certify_defaults, derived_defaults

ROOT = Path(__file__).resolve().parents[1]


class _UserAir3D(Air3D):
    """A user's system with Air3D's lemmas but no declared defaults: it gets the derived ones."""

    name = "user-air3d"

    def certification_defaults(self):
        return None


class _NoLemmas(_UserAir3D):
    name = "no-lemmas"

    def margin_step_bound(self, dt, integrator):
        return None


def test_air3d_declares_the_documented_settings_and_a_user_system_derives_the_same():
    declared = certify_defaults(Air3D(), 0.02)
    assert declared == {
        "level": 0.0,
        "escape_margin": 3.75,
        "closure_scale": 4,
        "closure_relative_width": 1 / 32,
        "min_relative_width": 1 / 32,
        "closure_refinements": 3,
    }
    assert certify_defaults(_UserAir3D(), 0.02) == declared == derived_defaults(Air3D(), 0.02)
    CertifySettings(time_to_go=1.1, dt=0.02, **declared)  # a valid proof
    # no bound on one step's loss of margin (RK4 here, or none declared): no escape set, the plain defaults
    assert derived_defaults(Air3D(), 0.02, "rk4") == {"level": 0.0}
    assert certify_defaults(_NoLemmas(), 0.02) == {"level": 0.0}
    # a larger box per dimension keeps the wide cover's cells within the budget: coarser cells in 6D
    assert derived_defaults(_UserAir3D(), 0.02)["closure_relative_width"] == 1 / 32


def test_a_declared_default_no_proof_takes_is_refused_by_name():
    class Bad(Air3D):
        name = "bad"

        def certification_defaults(self):
            return {"level": 0.0, "shortcut": True}

    with pytest.raises(ValueError, match=r"bad.certification_defaults names fields no proof takes: \['shortcut'\]"):
        certify_defaults(Bad(), 0.02)


@pytest.mark.slow
@pytest.mark.release
def test_reach_certify_with_no_options_reaches_ninety_percent_of_the_largest_invariant_set(tmp_path):
    """The documented Air3D certificate from ``reach certify pretrained:air3d --out c.npz`` alone: at
    least 90 % of the largest invariant set (the complement of the converged tube on a wider grid,
    benchmarks/invariant_reference.py), and the file re-verifies. About 20 minutes on 2 CPU cores (25 on
    CI's), so a release check (``python -m pytest -m release``), outside CI."""
    out = tmp_path / "c.npz"
    run = subprocess.run(
        [sys.executable, "-m", "reach", "certify", "pretrained:air3d", "--out", str(out)],
        capture_output=True, text=True, check=True, cwd=ROOT,
    )  # fmt: skip
    assert "air3d's certification defaults: level 0, escape_margin 3.75, closure_scale 4" in run.stdout
    reference = subprocess.run(
        [sys.executable, "benchmarks/invariant_reference.py", "--certificate", str(out),
         "--cache", str(tmp_path / "wide.npz")],
        capture_output=True, text=True, check=True, cwd=ROOT,
    )  # fmt: skip
    shares = r"certified ([0-9.]+) of the box, ([0-9.]+) of the largest invariant set; ([0-9.]+)"
    found = re.search(shares, reference.stdout)
    assert found, reference.stdout
    share_of_invariant, in_tube = float(found.group(2)), float(found.group(3))
    print(f"reach certify pretrained:air3d with its defaults: {found.group(0)}")  # shown with pytest -s (CI)
    assert share_of_invariant >= 0.90, reference.stdout
    assert in_tube < 1e-3, reference.stdout  # certified states are not in the grid's tube (up to its error)
    check = subprocess.run(
        [sys.executable, "-m", "reach", "certify", "pretrained:air3d", "--check", str(out)],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert check.returncode == 0 and "holds for pretrained:air3d" in check.stdout, check.stderr


def test_an_option_given_alone_keeps_the_other_defaults_consistent():
    """--closure-scale alone moves the default escape set with it (as far out as the lemmas allow at
    that scale); every field given is left to the caller."""
    scaled = certify_defaults(Air3D(), 0.02, given={"closure_scale": 1})
    assert scaled["escape_margin"] == Air3D().margin_outside_domain(1.0) == 0.75 and "closure_scale" not in scaled
    assert "escape_margin" not in certify_defaults(Air3D(), 0.02, given={"closure_scale": 2, "escape_margin": 1.0})
    assert certify_defaults(Air3D(), 0.02, given={"level": 0.1})["closure_scale"] == 4
