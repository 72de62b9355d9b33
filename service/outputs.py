"""Standard animation outputs of a session: MPEG-4 FAPs and ARKit blendshapes per frame.

Built once per session from its model (``hello``'s description); the head FAPs are relative
to the session's first good frame (the speaker's own neutral head pose: a head-mounted camera
does not look at the face frontally), which is what players expect of a ``head_pitch = 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from articast.core.errors import InputError


class Outputs:
    """Per-frame FAP and ARKit values of one session's model."""

    def __init__(self, model: Any) -> None:
        from articast.core.outputs.arkit import ArkitMapper
        from articast.core.outputs.fap import FapEncoder, fapu_from_model

        self.model = model
        self.fapu = fapu_from_model(model).as_dict()
        self._fap_cls = FapEncoder
        self._fap: Any = None
        self._fap_ref: tuple[float, ...] = ()
        self.arkit = ArkitMapper(model)

    def fap(self, alpha: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
            ok: bool, neutral_rotation: Any = None) -> dict[str, Any]:
        """FAPs of one frame; the head FAPs are relative to ``neutral_rotation`` (the
        session's neutral head pose), or without one to the first good frame seen here."""
        if neutral_rotation is not None and (self._fap is None
                                             or tuple(neutral_rotation) != self._fap_ref):
            self._fap_ref = tuple(neutral_rotation)
            self._fap = self._fap_cls(self.model, reference_rotation=np.asarray(self._fap_ref))
        if self._fap is None:
            if not ok:  # no reference head pose yet: nothing sensible to say
                return {"values": {}, "mask": []}
            self._fap_ref = tuple(float(v) for v in rotation)
            self._fap = self._fap_cls(self.model, reference_rotation=np.asarray(rotation))
        values = self._fap.frame_dict(alpha, np.concatenate([rotation, translation]))
        return {"values": values, "mask": sorted(int(k) for k in values)}

    def with_upper_fap(self, fap: dict[str, Any], upper: Any) -> dict[str, Any]:
        """A frame's FAPs with the eyelid, eyeball and eyebrow FAPs of ``upper`` (an
        :class:`~articast.core.faces.upper.UpperFace`) added where they were seen."""
        from articast.core.outputs.fap import Fapu
        from articast.core.outputs.upper import fap_upper

        extra = fap_upper(upper, Fapu(**self.fapu))
        if not extra or self._fap is None:  # nothing seen, or no reference head pose yet
            return fap
        values = {**fap["values"], **{str(k): int(v) for k, v in extra.items()}}
        return {"values": values, "mask": sorted(int(k) for k in values)}

    def recentre(self) -> None:
        """The next good frame becomes the head FAPs' reference (as the session's neutral)."""
        self._fap = None

    def arkit_weights(self, alpha: np.ndarray) -> dict[str, float]:
        return self.arkit.weights_dict(np.asarray(alpha))


def make_outputs(desc: dict[str, Any]) -> Outputs | None:
    """Outputs for a session description, or None when its model cannot produce them."""
    from articast.service.wire import model_from_description

    model = model_from_description(desc)
    if model is None:
        return None
    try:
        return Outputs(model)
    except InputError:
        return None  # e.g. a model without the MPEG-4 feature points
