"""Where models come from: a folder the user names, or the default model shipped in the package."""

from __future__ import annotations

from pathlib import Path

from estimator.contract import AGGREGATOR_FILE, BACKBONE_FILE
from rig.errors import ModelError

# The shipped default model lives here once one is trained (see docs/model.md); until then the
# folder is absent and every command that needs a model asks for --model.
DEFAULT_MODEL_DIR = Path(__file__).resolve().parent / "default_model"


def resolve_model_dir(model_dir: str | Path | None) -> Path:
    """The folder to load: ``model_dir`` if given, else the shipped default."""
    if model_dir is not None:
        return Path(model_dir)
    if (DEFAULT_MODEL_DIR / BACKBONE_FILE).is_file() and (DEFAULT_MODEL_DIR / AGGREGATOR_FILE).is_file():
        return DEFAULT_MODEL_DIR
    raise ModelError(
        "no model given and no default model is installed: pass --model DIR "
        f"(a folder with {BACKBONE_FILE} and {AGGREGATOR_FILE}, e.g. the --out of `sunrig train`)"
    )
