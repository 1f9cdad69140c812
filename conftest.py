"""Repository-wide pytest set-up: docstring examples run in a fresh temporary folder.

``python3 -m pytest`` collects the examples in ``diffloc/`` (``--doctest-modules``); an example
that writes ``frame.png`` writes it into its own ``tmp_path``, never into the checkout.
"""

import pytest
from _pytest.doctest import DoctestItem


@pytest.fixture(autouse=True)
def _doctests_run_in_a_temporary_folder(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
):
    if isinstance(request.node, DoctestItem):
        with pytest.MonkeyPatch.context() as patch:
            patch.chdir(tmp_path_factory.mktemp("doctest"))
            yield
    else:
        yield
