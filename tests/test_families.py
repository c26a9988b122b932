"""The family registry: every consumer names the same families, and a deprecated alias warns."""

from __future__ import annotations

import inspect
import warnings

import pytest
import torch

import torchcage
from torchcage import functional as F
from torchcage.families import ALIASES, FAMILIES, family, names
from torchcage.image import CageWarp


def test_registry_entries_resolve_to_public_code() -> None:
    for fam in FAMILIES:
        fn, module = fam.function(), fam.module()
        assert getattr(F, fn.__name__) is fn, fam.short  # the public functional name
        assert getattr(torchcage, module.__name__) is module, fam.short
        assert issubclass(module, torch.nn.Module)
        params = inspect.signature(fn).parameters
        assert "tol" in params or not fam.tol, fam.short  # (mec has its own solver tolerance)
        assert ("backend" in params) == bool(fam.backends), fam.short


def test_consumers_read_the_registry() -> None:
    from torchcage import methods
    from torchcage.functional.deform import OUTSIDE_EFFECT
    from torchcage.splats.deform import METHODS as SPLAT_METHODS

    assert methods.METHODS == names()
    assert set(OUTSIDE_EFFECT) == set(names())
    assert all(family(m).jacobian for m in SPLAT_METHODS)
    for fam in FAMILIES:
        assert fam.short in methods.METHOD_HELP and methods.METHOD_NAMES[fam.short] == fam.name


def test_unknown_name_lists_the_choices() -> None:
    with pytest.raises(ValueError, match="must be one of mvc, gc"):
        family("cuda")
    with pytest.raises(ValueError, match="must be one of mvc, qmvc"):
        family("lbc", ["mvc", "qmvc"])


@pytest.mark.parametrize("alias", sorted(ALIASES))
def test_alias_warns_and_gives_the_same_result(alias: str) -> None:
    pytest.importorskip("kornia", reason="image warping needs kornia (torchcage[image])")
    square = torch.tensor([[2.0, 2], [13, 2], [13, 13], [2, 13]], dtype=torch.float64)
    with pytest.warns(DeprecationWarning, match=f"{alias!r} is deprecated") as caught:
        old = CageWarp(square, 16, 16, method=alias)
    assert caught[0].filename == __file__  # the warning points at the caller's line
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = CageWarp(square, 16, 16, method=ALIASES[alias])
    assert old.method == new.method == ALIASES[alias]
    img = torch.rand(1, 1, 16, 16, dtype=torch.float64)
    pose = square * 0.9 + 1
    assert torch.equal(old(img, pose), new(img, pose))
    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    x = torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64)
    with pytest.warns(DeprecationWarning):
        y = torchcage.deform(x, cube, cube.vertices * 2, method=alias)
    torch.testing.assert_close(y, 2 * x)


def test_modules_saved_under_the_old_paths_still_load() -> None:
    """A module pickled when its class lived in ``torchcage.nn.mean_value`` (before the families'
    folders) unpickles to the same module and the same deformation."""
    import pickle

    cube = torchcage.load_cage(torchcage.data.path("cube.obj")).triangulated()
    m = torchcage.MeanValueCoordinates(cube, torch.tensor([[0.1, 0.2, -0.3]], dtype=torch.float64))
    data = pickle.dumps(m, protocol=0)  # (text protocol: module paths are plain lines)
    assert b"torchcage.families.mean_value.module" in data
    old = data.replace(b"torchcage.families.mean_value.module", b"torchcage.nn.mean_value")
    back = pickle.loads(old)
    assert type(back) is torchcage.MeanValueCoordinates
    pose = cube.vertices * 2 + 1
    torch.testing.assert_close(back(pose), m(pose), rtol=0, atol=0)
