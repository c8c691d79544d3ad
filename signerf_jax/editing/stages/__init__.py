"""The SIGNeRF pipeline (paper, Sec. 3 "Scene Integrated Generation"), one module per stage.

  original     1. train the original NeRF on the dataset's training views (or use a given run)
  select       2. the box or placed proxy, checked against the dataset            (inputs.py)
  reference    3-4. place the reference cameras; render their tiles            (reference.py)
  preview      candidate sheets for several seeds (and re-rolls) side by side    (sheets.py)
  sheet        5. the chosen sheet (a recipe: seed and re-rolled tiles)
  views        the mask and control depth of every training view, from the original NeRF
               (after the preview, which needs only the reference tiles)        (inputs.py)
  update       6. the image set update (vmapped, sharded, resumable per view) (propagation.py)
  dataset      the edited dataset in nerfstudio format, with provenance
  finetune     7. fine-tune the original NeRF on it, or retrain from scratch (nerf_update.py)
  *_2          8. optionally: reference (rendered by the edited NeRF), sheet, update, dataset
               and finetune once more, with the second iteration's GenerationOptions
  evaluate     background preservation, consistency, CLIP, adherence, renders, video
                                                                              (evaluate.py)

Each stage is a function `stage(context) -> summary line` of an `EditContext` (context.py: the
edit directory, the `EditSettings`, and the inputs earlier stages wrote, loaded once); the
runner (runner.py) orders them, computes their keys, skips finished ones and times the rest.
"""

from signerf_jax.editing.stages.context import EditContext
from signerf_jax.editing.stages.runner import (RunTraining, Stage, claimed_edit, edit_key,
                                               pipeline_stages, run_edit)

__all__ = ["EditContext", "RunTraining", "Stage", "claimed_edit", "edit_key", "pipeline_stages",
           "run_edit"]
