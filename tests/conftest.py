import pytest
from factories import make_info

from pipeline.dataset import DatasetInfo


@pytest.fixture
def info() -> DatasetInfo:
    return make_info()
