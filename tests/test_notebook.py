"""notebooks/room_tour.ipynb: committed without outputs, and it runs headless (nbclient) from a scratch
working folder, building its own tiny sequence, without a cell error."""
from __future__ import annotations

import shutil

import pytest

from tests.conftest import REPO

nbformat = pytest.importorskip("nbformat", reason="nbformat not installed (pip install nbformat)")
nbclient = pytest.importorskip("nbclient", reason="nbclient not installed (pip install nbclient ipykernel)")
pytest.importorskip("ipykernel", reason="ipykernel not installed (pip install ipykernel)")

NOTEBOOK = REPO / "notebooks" / "room_tour.ipynb"


def test_committed_notebook_is_valid_and_has_no_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code
    for c in code:
        assert c.outputs == [] and c.execution_count is None


def test_notebook_runs_headless_on_a_tiny_sequence(tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    shutil.copy(NOTEBOOK, work / NOTEBOOK.name)
    monkeypatch.setenv("ROOM_DATASET", str(tmp_path / "absent"))   # no dataset there: the notebook builds one
    monkeypatch.setenv("TMPDIR", str(tmp_path))                    # ... in a folder the test owns
    nb = nbformat.read(work / NOTEBOOK.name, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(work)}})
    client.execute()   # raises CellExecutionError on the first cell that fails
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream" and o.name == "stdout")
    assert "built a tiny one" in text and "10 frames" in text
    assert "depth:" in text and "mm over" in text
    assert "benchmark result file(s)" in text
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 3                     # modalities, point cloud, trajectory (+ tracking error)
    assert list(tmp_path.glob("room_tour_*/output/patient_demo/sequence_000/rgb/frame_0009.png"))
