import os

import pytest
import torch

# Tests must not depend on the developer's thread settings; two threads like CI.
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture(scope="session")
def ext():
    """The compiled C++ rasteriser (built once per machine, then cached)."""
    from kgs_core.render import _ext

    return _ext.load()
