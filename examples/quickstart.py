"""ltcal from Python: the README's first section, in a script.

Runs the synthetic validation (the paper's Figure 8 reproduced), plots
Figure 8's errors before and after the calibration with matplotlib, and
diagnoses an example campaign held in DataFrames.

    pip install .            # from the repository
    python examples/quickstart.py [OUT]   # figures and diagnosis into OUT

Run it from the repository's root (the pipeline and campaign paths are
relative to it); OUT defaults to a new temporary folder.
"""

import os
import sys
import tempfile

import matplotlib

matplotlib.use("Agg")  # files, not windows: runs headless
import matplotlib.pyplot as plt  # noqa: E402

import ltcal  # noqa: E402

out = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="ltcal-quickstart-")
os.makedirs(out, exist_ok=True)

# 1. The synthetic validation: cached stages cost nothing on a second run.
run = ltcal.run("pipelines/synthetic-validation.toml")
print(run)
print(run.table("evaluate_sphere.summary"))

# 2. Figure 8: the error at each of the 480 reflectors, before and after.
points = run.table("evaluate_sphere.points")
fig, ax = plt.subplots(figsize=(7, 4))
ax.plot(points["err_before_um"].to_numpy(), ".", label="before calibration")
ax.plot(points["err_after_um"].to_numpy(), ".", label="after calibration")
ax.set_yscale("log")
ax.set_xlabel("reflector")
ax.set_ylabel("error (µm)")
ax.set_title("Figure 8: errors in a spherical mesh")
ax.legend()
figure = os.path.join(out, "figure8.png")
fig.savefig(figure, dpi=100)
print(f"Figure 8 written to {figure}")

# 3. A campaign held in DataFrames (here read from an example folder; any
#    pandas DataFrames with the format's columns will do), diagnosed.
campaign = ltcal.read_campaign("examples/campaigns/example-05-station-drift")
print(campaign.readings.head())
diagnosis = ltcal.diagnose(campaign, out=os.path.join(out, "diagnosis"))
print(diagnosis.verdict)
print(diagnosis.tables["diagnosis"].head())
print(f"figures: {', '.join(os.path.basename(f) for f in diagnosis.figures)}")
