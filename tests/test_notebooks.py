"""Every notebook in notebooks/ executes from top to bottom without error."""

from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat", reason="notebook tests need the 'dev' extra")
nbclient = pytest.importorskip("nbclient", reason="notebook tests need the 'dev' extra")

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_notebooks_found():
    assert NOTEBOOKS, "no notebooks found"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_executes(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    if path.name == "oscillator.ipynb":
        # The gradient through 500 implicit steps matches the exact derivative (h^4 ~ 1e-8).
        values = {line.split(":")[0].strip(): float(line.split(":")[1])
                  for line in text.splitlines() if line.startswith(("autodiff", "exact"))}
        assert values["autodiff"] == pytest.approx(values["exact"], rel=1e-6)
        assert "failed: non-finite values" in text
    if path.name == "car_pendulum.ipynb":
        values = {line.split(":")[0].strip(): float(line.split(":")[1])
                  for line in text.splitlines() if line.startswith(("autodiff", "central"))}
        # Central difference with step 1e-5: truncation ~1e-10, cancellation ~1e-11.
        assert values["autodiff"] == pytest.approx(values["central difference"], rel=1e-6)
        assert "hamel-exact" in text and "all 4000 steps succeeded" in text
    if path.name == "inertia_fitting.ipynb":
        values = {line.split(":")[0].strip(): line.split(":", 1)[1].strip()
                  for line in text.splitlines() if ":" in line}
        # Noise-free fit over 2 s at h = 0.01 from the paper's inertia (20% off).
        assert float(values["start relative error"]) > 0.15
        assert float(values["relative error of J_c"]) <= 0.01
        assert values["physical"] == "True"
        assert values["smallest principal moment > 0"] == "True"
        assert values["triangle inequalities hold"] == "True"
