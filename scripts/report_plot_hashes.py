"""Usage: PYTHONPATH=SRC python scripts/report_plot_hashes.py (from the repo root), once with the old src and once with
the new.  sha256 of each benchmark plot's PNG and its caption note (report/plots.py), for a before/after comparison;
also the simulation file with one row marked unstable."""
import copy, hashlib, json
from pathlib import Path
from room_pipeline.report import plots
d = Path("benchmarks/results")
new = isinstance(plots.BENCHMARK_PLOTS[0], plots.PlotSpec) if hasattr(plots, "PlotSpec") else False
def plot(stem, doc):
    if new:
        return plots.build_plot({s.stem: s for s in plots.BENCHMARK_PLOTS}[stem], doc)
    return dict(plots.BENCHMARK_PLOTS)[stem](doc)
for stem in ["mesh_decimation", "sdf_methods", "simulation", "raycast_renderer", "cycles_quality", "simulation*"]:
    doc = json.loads((d / f"{stem.rstrip('*')}.json").read_text())
    if stem.endswith("*"):
        doc = copy.deepcopy(doc); doc["speed_vs_error"][0]["stable"] = False; doc["speed_vs_error"][3]["stable"] = False
    p = plot(stem.rstrip("*"), doc)
    print(stem, hashlib.sha256(plots.plot_png(p)).hexdigest()[:16], p.title, "|", p.note)
