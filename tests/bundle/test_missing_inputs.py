"""Both inference workflows refuse a missing dataset folder or weights file with one line naming the path."""

from __future__ import annotations

import pytest
from bundle_fixtures import infer_workflow, root_cause

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.mark.parametrize("config", ["inference.yaml", "evaluate.yaml"])
@pytest.mark.parametrize("missing", ["dataset_dir", "model_file"])
def test_missing_input_gives_one_line_error_naming_the_path(tmp_path, tiny_dataset, bundle, config, missing):
    path = tmp_path / "does_not_exist"
    wf = infer_workflow(config, bundle, tiny_dataset, tmp_path / "out", **{missing: str(path)})
    with pytest.raises(Exception) as info:
        wf.run()
    cause = root_cause(info.value)
    assert isinstance(cause, FileNotFoundError)
    assert str(path) in str(cause) and "\n" not in str(cause)
    assert not (tmp_path / "out").exists()  # nothing half-written
