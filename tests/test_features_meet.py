"""Where features meet (issue 31): small things a user trips on, each where the user meets it."""

import warnings
from types import SimpleNamespace

import pytest

from spread.guidance import GuidanceConfig
from spread.sampling.worker import warn_graph_guidance


@pytest.mark.parametrize("method, warned", [("diffuscene", True), ("atiss", True), ("spread", False),
                                            ("instructscene", False)])
def test_relation_guidance_on_a_method_not_trained_with_graphs_is_said(method, warned):
    model = SimpleNamespace(hparams={"method": method})
    guided = GuidanceConfig(mode="paper", relation=1e-3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_graph_guidance(guided, model, "x.ckpt")
        warn_graph_guidance(GuidanceConfig(mode="paper", relation=0.0), model, "x.ckpt")  # no relation: silent
    said = [w for w in caught if "not trained with the graphs" in str(w.message)]
    assert len(said) == (1 if warned else 0)
    if warned:
        assert f"'{method}'" in str(said[0].message) and "guidance.relation=0" in str(said[0].message)
