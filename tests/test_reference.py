"""Behaviour held fixed: a fresh run of each reference scene (tests/reference_runs.py)
against the run file recorded before the code was restructured.

Bit-identical is expected where the arithmetic is unchanged.  Where a change of summation
order makes a value differ, the test allows at most 1e-12 relative on sigma(gamma) and 1e-9
on everything else, and prints the largest difference of each entry that is not identical
(run with -s to see it)."""
import os

import h5py
import pytest

import reference_runs as ref

pytestmark = pytest.mark.serial_only     # the step sequence itself is compared, row by row

SIGMA_RTOL = 1e-12
OTHER_RTOL = 1e-9


@pytest.mark.parametrize("name", sorted(ref.SCENES))
def test_reference_scene_unchanged(tmp_path, name):
    if not os.path.exists(ref.reference_path(name)):
        pytest.fail(f"no reference for {name}: run tests/reference_runs.py")
    path = str(tmp_path / f"{name}.h5")
    assert ref.run(name, path) == "complete"
    with h5py.File(path, "r") as f:
        new = ref.flatten(f)
    old = ref.load_reference(name)
    made_with = str(old.pop(ref.KERNELS_KEY, "unrecorded"))
    assert made_with == ref.kernels(), (
        f"{name}: reference made with kernels '{made_with}', this run uses '{ref.kernels()}': "
        "the arithmetic differs at round-off; run under scripts/env.sh (it pins them)")
    diffs = ref.differences(old, new)
    changed = {k: v for k, v in diffs.items() if v > 0}
    for k, v in sorted(changed.items()):
        print(f"{name}: {k}: largest relative difference {v:.3g}")
    missing = sorted(k for k, v in changed.items() if v == float("inf"))
    assert not missing, f"entries added, removed, reshaped or changed in kind: {missing[:20]}"
    sigma = {k: v for k, v in changed.items() if k == "timeseries/sigma"}
    assert all(v <= SIGMA_RTOL for v in sigma.values()), sigma
    worst = {k: v for k, v in changed.items() if v > OTHER_RTOL}
    assert not worst, worst
