"""Official checkpoints -> occkit weights: FlashOcc / BEVDet and DAOcc state dicts renamed, re-laid and checked.

``occkit convert CKPT --model ENTRY --out FILE.safetensors`` reads a checkpoint of a reference implementation,
maps every tensor onto the parameter of the zoo entry's model that plays its part, and writes them with a report::

    conversion = convert_checkpoint("epoch_24_ema.pth", "daocc", "daocc.safetensors")   # + daocc.report.json
    model = load_weights("daocc.safetensors", "daocc")                                   # strict, shape-checked

Sources (told apart by their key prefixes, :func:`detect_source`), each with its rename rules in a module:

* ``flashocc``: FlashOcc's ``BEVDetOCC`` and BEVDet's detection model (:mod:`occkit.convert.flashocc`).
* ``daocc``: DAOcc's ``BEVFusion`` (:mod:`occkit.convert.daocc`).
* ``occkit``: weights already in occkit's names (a converted ``.safetensors``, an occkit checkpoint).

Where a reference lays a tensor out otherwise than occkit (BEV maps as ``(Y, X)``, spconv 1.x kernels), the tensor
is re-laid, not only renamed (:mod:`occkit.convert.rules`). Everything else maps key for key. Keys a reference keeps
that occkit does not need are dropped with a reason (sampling-point buffers occkit computes from the config, BEVDet's
detection head, ``num_batches_tracked`` where occkit's module has none); any other difference (a key without
counterpart, an occkit tensor left unfilled, a shape that differs) is an error in strict mode, naming the keys.
Non-strict mode (``train.load_from``, :func:`load_partial`) loads what fits and lists the rest.

Files are read with ``torch.load(weights_only=True)`` (numpy scalars and arrays in mmcv's ``meta`` are allowed; they
rebuild plain data), never by unpickling code (:func:`occkit.weight_files.read_checkpoint`).

Modules: :mod:`~occkit.convert.rules` (what a table is made of), :mod:`~occkit.convert.mmdet_modules` (rules of the
modules both references share), one module per reference, :mod:`~occkit.convert.conversion` (detecting the source,
applying its rules, checking the result) and :mod:`~occkit.convert.weights` (the converted file and its report,
loading weights into a model).
"""

from occkit.convert.conversion import (
    SOURCES,
    Conversion,
    ShapeMismatch,
    convert_state_dict,
    default_entry,
    detect_source,
)
from occkit.convert.rules import Source
from occkit.convert.weights import (
    PartialLoad,
    convert_checkpoint,
    format_report,
    load_partial,
    load_weights,
    report_path,
)
from occkit.weight_files import WEIGHTS_FORMAT, ReferenceCheckpoint, read_checkpoint

__all__ = [
    "WEIGHTS_FORMAT",
    "Source",
    "SOURCES",
    "ShapeMismatch",
    "Conversion",
    "ReferenceCheckpoint",
    "PartialLoad",
    "read_checkpoint",
    "detect_source",
    "default_entry",
    "convert_state_dict",
    "convert_checkpoint",
    "report_path",
    "format_report",
    "load_weights",
    "load_partial",
]
