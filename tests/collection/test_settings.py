"""What is the same for every image of a run (``torchiid.collection.settings``)."""

import json

from torchiid.collection import RunSettings, params_hash
from torchiid.params import Parameters


def test_the_parameters_hash_does_not_depend_on_the_version(monkeypatch, tmp_path):
    # a new version that computes the same files keeps a collection's records
    import torchiid

    settings = RunSettings(out=tmp_path, params=Parameters.preset("converged"))
    before = params_hash(settings)
    monkeypatch.setattr(torchiid, "__version__", "99.0.0")
    assert json.loads(settings.params.to_json())["torchiid_version"] == "99.0.0"
    assert params_hash(settings) == before
    assert params_hash(RunSettings(out=tmp_path, params=Parameters())) != before
