"""Where models come from: a folder the user names, or the default model shipped in the package."""

from __future__ import annotations

from pathlib import Path

from estimator.contract import AGGREGATOR_FILE, BACKBONE_FILE
from rig.errors import ModelError

# The shipped default model (docs/model.md). An install without it (a source tree whose graphs
# were removed) makes every command that needs a model ask for --model.
DEFAULT_MODEL_DIR = Path(__file__).resolve().parent / "default_model"
# `train --init shipped`: fine-tune the installed model without spelling out where pip put it.
SHIPPED = "shipped"


def resolve_model_dir(model_dir: str | Path | None) -> Path:
    """The folder to load: ``model_dir`` if given, else the shipped default."""
    if model_dir is not None:
        return Path(model_dir)
    if _default_installed():
        return DEFAULT_MODEL_DIR
    raise ModelError(
        "no model given and no default model is installed: pass --model DIR "
        f"(a folder with {BACKBONE_FILE} and {AGGREGATOR_FILE}, e.g. the --out of `sunrig train`)"
    )


def resolve_init_dir(init: str) -> Path:
    """``train --init``'s folder: the word ``shipped`` is the installed default model.

    A folder named ``shipped`` in the working directory makes the word ambiguous, so it is
    refused rather than guessed; ``./shipped`` names the folder."""
    if init != SHIPPED:
        return Path(init)
    if Path(init).exists():
        raise ModelError(f"--init {SHIPPED}: ./{SHIPPED} also exists here; write ./{SHIPPED} to start from "
                         "that folder, or run from another directory to start from the shipped model")
    if not _default_installed():
        raise ModelError(f"--init {SHIPPED}: no shipped model is installed (no graphs in {DEFAULT_MODEL_DIR}); "
                         "pass a model folder written by `sunrig train`")
    return DEFAULT_MODEL_DIR


def is_shipped(model_dir: str | Path) -> bool:
    """Whether ``model_dir`` is the shipped default model's folder (by whatever path it is named)."""
    try:
        return Path(model_dir).resolve() == DEFAULT_MODEL_DIR
    except OSError:  # a path that cannot be resolved (a loop of links) is not ours
        return False


def _default_installed() -> bool:
    return (DEFAULT_MODEL_DIR / BACKBONE_FILE).is_file() and (DEFAULT_MODEL_DIR / AGGREGATOR_FILE).is_file()
