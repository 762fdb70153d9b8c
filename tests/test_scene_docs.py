"""docs/scenes.md against the schema the code uses (scene.SCHEMA, built from the section
dataclasses, and each model's PARAMS): every key is documented, with its real default."""
import os
import re
import tomllib

import pytest

from parflow.models import MODELS, get_model
from parflow.scene import SCHEMA, load_scene

pytestmark = pytest.mark.serial_only      # reads files; nothing MPI about it

DOCS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs")


def _blocks(name):
    with open(os.path.join(DOCS, name)) as fh:
        text = fh.read()
    return text, [tomllib.loads(b) for b in re.findall(r"```toml\n(.*?)```", text, re.S)]


def test_every_scene_key_is_documented_with_its_default():
    text, blocks = _blocks("scenes.md")
    full = blocks[0]                                    # the annotated scene at the top
    for section, keys in SCHEMA.items():
        doc = full if section == "" else full.get(section, {})
        for name, k in keys.items():
            if name == "leg":
                assert isinstance(full["protocol"]["leg"], list)
                continue
            assert name in doc, f"docs/scenes.md lacks {section or 'top-level'}.{name}"
            if k.default is not None:
                assert doc[name] == k.default, \
                    f"docs/scenes.md gives {section}.{name} = {doc[name]!r}, the code {k.default!r}"
    # the documented scene is a valid scene, and so is each stop rule it names
    load_scene(re.findall(r"```toml\n(.*?)```", text, re.S)[0].replace(
        'tau_pc_factor_mat_solver_type = "mumps"', ""))
    for rule in SCHEMA["protocol"]:
        assert rule in text


def test_every_model_key_is_documented():
    """Each model's [model] keys appear in docs/scenes.md or in the model's own page, and a
    documented example table gives the code's defaults."""
    pages = {"chain": "chain.md", "network": "networks.md", "suspension": "suspensions.md"}
    text, blocks = _blocks("scenes.md")
    for name in MODELS:
        params = get_model(name).PARAMS
        other = open(os.path.join(DOCS, pages[name])).read() if name in pages else ""
        for key in params:
            assert re.search(rf"\b{re.escape(key)}\b", text + other), \
                f"model {name}: key {key!r} is documented nowhere"
        for b in blocks:
            m = b.get("model", {})
            if m.get("name") == name:
                for key, value in m.items():
                    if key != "name":
                        assert key in params, f"docs/scenes.md: model {name} has no key {key!r}"
                        assert value == params[key][1], (name, key, value, params[key][1])


def test_nested_petsc_tables_name_a_prefix():
    base = 'seed = 1\n[model]\nname = "chain"\nN = 20\n[[protocol.leg]]\ndirection = "forward"\nstrain = 0.1\n'
    s = load_scene(base + '[petsc]\ntau_ksp_rtol = 1e-9\n[petsc.tau]\nksp_type = "cg"\n'
                   '[petsc.spec.eps]\nncv = 32\n')
    assert s["petsc"] == {"tau_ksp_rtol": 1e-9, "tau_ksp_type": "cg", "spec_eps_ncv": 32}
    from parflow.state import InputError
    with pytest.raises(InputError, match="given twice"):
        load_scene(base + '[petsc]\ntau_ksp_type = "gmres"\n[petsc.tau]\nksp_type = "cg"\n')
    with pytest.raises(InputError, match="one word"):
        load_scene(base + '[petsc.tau]\nksp_type = "c g"\n')
