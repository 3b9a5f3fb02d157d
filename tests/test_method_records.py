"""gp_model's and gp_critic's records on the tiny preset and every standard preset (2 seeds and 2
updates; the double pendulum 1 and 1; float64, as `gpguided reproduce` runs them) are those of
tests/data/model_critic_records.npz, written by tests/data/make_method_records.py before their
settings moved into their own modules: a change of structure must leave their numbers as they are.
The tolerance allows for another CPU's vector width, no more (the file's own machine reproduces it
bit for bit)."""

import importlib.util
import os

import numpy as np
import pytest

pytestmark = pytest.mark.training  # a reproduce run per preset

HERE = os.path.dirname(os.path.abspath(__file__))
_spec = importlib.util.spec_from_file_location("make_method_records",
                                               os.path.join(HERE, "data", "make_method_records.py"))
make = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make)


@pytest.mark.parametrize("preset", make.PRESETS)
def test_the_records_equal_their_reference_file(preset):
    with np.load(make.OUT) as ref:
        expected = {k: ref[k] for k in ref.files if k.startswith(f"{preset}/")}
    assert {k.split("/")[1] for k in expected} == set(make.METHODS)
    got = make.records(preset)
    assert sorted(got) == sorted(expected)
    for name, want in expected.items():
        np.testing.assert_allclose(got[name], want, rtol=1e-9, atol=1e-12, err_msg=name)
