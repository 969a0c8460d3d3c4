"""The tables read real data when ``$NRSFM_DATA`` holds it: their tests run on the embedded stand-ins unless they
are marked ``realdata`` (or pass ``--root`` themselves)."""

import pytest


@pytest.fixture(autouse=True)
def _stand_in_unless_realdata(request, monkeypatch):
    if request.node.get_closest_marker("realdata") is None:
        monkeypatch.delenv("NRSFM_DATA", raising=False)
