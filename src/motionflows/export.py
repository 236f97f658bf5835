"""``motionflows export RUN --out DIR``: a run directory to ship (no optimiser state).

The export holds ``config.json``, ``standardizer.json``, ``metrics.jsonl``, the run's
``eval_*.json`` tables and ``checkpoints/best/<step>/`` with the model's parameters and
other variables only (the optimiser state, two thirds of a checkpoint for Adam, is left
out), so it loads with :func:`motionflows.run.load_run` and
:class:`motionflows.pretrained.PretrainedModel` like the run itself. ``pretrained.json``
records the validated sampling temperature. An export of a model trained on the Bandai
data carries that data's licence note.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from flax import nnx

from motionflows.checkpoints import Checkpointer
from motionflows.errors import RunError

COPIED = ("config.json", "standardizer.json", "metrics.jsonl", "loss.png")
BANDAI_NOTE = """# Licence of these weights

This model was trained on the Bandai-Namco-Research-Motiondataset
("Bandai-Namco-Research-Motiondataset, (c) 2022 Bandai Namco Research Inc., CC BY-NC 4.0",
https://github.com/BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset, cite Kobayashi
et al., arXiv:2306.08861, 2023). Weights trained on that data inherit its terms: **non-commercial
use only, with attribution** (CC BY-NC 4.0, https://creativecommons.org/licenses/by-nc/4.0/).
The motionflows code itself is MIT-licensed.
"""


def export_run(
    run_dir: str | Path,
    out: str | Path,
    *,
    checkpoint: str = "best",
    temperature: float | None = None,
    notes: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the shippable copy of ``run_dir`` to ``out`` and return ``out``.

    ``temperature``: the sampling temperature validated for this model (stored in
    ``pretrained.json``; default 1.0 when loading). ``overwrite`` replaces an existing
    export (a folder with ``pretrained.json``); any other non-empty ``out``, the run itself,
    a folder holding it or one inside it is refused.
    """
    from motionflows import runs
    from motionflows.models.validation import check_temperature
    from motionflows.run import load_standardizer, restore_run

    run_dir = runs.check_run_dir(run_dir)
    if temperature is not None:
        check_temperature(temperature, "export_run")
    load_standardizer(run_dir)  # an export without a readable one could not be loaded
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RunError(f"--out {out} is a file; give a folder for the exported run")
    target, source = out.resolve(), run_dir.resolve()
    if target == source or target in source.parents:
        raise RunError(f"--out {out} holds the run {run_dir}; choose a folder outside it")
    if source in target.parents:
        raise RunError(f"--out {out} is inside the run {run_dir}; choose a folder outside it")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise RunError(f"--out {out} is not empty; choose a new folder (or pass --overwrite)")
        if not (out / "pretrained.json").is_file():
            raise RunError(
                f"--out {out} is not an export (no pretrained.json): --overwrite replaces only "
                "an earlier export; choose a new or empty folder"
            )
    module, config, model, saved = restore_run(run_dir, checkpoint=checkpoint)
    _, params, rest = nnx.split(model, nnx.Param, ...)
    which, meta = saved["which"], saved["meta"]
    step = int(meta["step"])
    # written next to ``out`` and moved into place at the end: a failure on the way leaves
    # an existing export as it was
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; an export is meant to be shared
    try:
        _write_export(run_dir, tmp, params, rest, step, meta, which)
        info = {"experiment": module.NAME, "step": step, "checkpoint": which}
        if temperature is not None:
            info["temperature"] = float(temperature)
        if notes:
            info["notes"] = notes
        (tmp / "pretrained.json").write_text(json.dumps(info, indent=2) + "\n")
        if config.data.source == "bandai":
            (tmp / "LICENSE.md").write_text(BANDAI_NOTE)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _write_export(run_dir: Path, out: Path, params, rest, step: int, meta: dict, which: str):
    """The copied files and the parameters-only checkpoint ``out/checkpoints/best/<step>``."""
    for name in COPIED:
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, out / name)
    for table in sorted(run_dir.glob("eval_*.json")):
        shutil.copy2(table, out / table.name)
    meta = {k: v for k, v in meta.items() if k not in ("opt",)}
    # experiment/run-name: where it came from, without the exporting machine's paths
    meta.update(exported_from=f"{run_dir.parent.name}/{run_dir.name}", exported_checkpoint=which)
    target = Checkpointer(out / "checkpoints", keep=1)
    try:
        target.save(step, {"params": params, "rest": rest}, meta, which="best")
    finally:
        target.close()
    latest = out / "checkpoints" / "latest"
    if latest.is_dir() and not any(latest.iterdir()):  # the manager's empty folder
        latest.rmdir()
