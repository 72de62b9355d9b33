"""The 68 MPEG-4 facial animation parameters (FAP.md, ``docs/fap_table.csv``).

One :class:`FapSpec` per FAP: number, name, unit (FAPU), uni/bidirectional, positive direction,
feature point moved and the quantisation step of the reference (binary) encoder. The table is
data, copied verbatim from the project's cross-checked CSV; :mod:`articast.core.outputs.fap`
gives it meaning.
"""

from __future__ import annotations

from dataclasses import dataclass

N_FAPS = 68
"""Number of FAPs; a ``.fap`` mask line has exactly this many flags."""


@dataclass(frozen=True)
class FapSpec:
    """One row of the FAP table.

    number : 1..68. unit : ``"MNS"``, ``"MW"``, ``"ENS"``, ``"ES"``, ``"IRISD"``, ``"AU"`` or
    ``"na"``. bidirectional : False for the unidirectional FAPs (``U``). direction : the
    positive motion (``"up"``, ``"down"``, ``"left"``, ``"right"``, ``"forward"``...), left and
    right being the face's own sides. feature_point : MPEG-4 label of the point moved.
    quant_step : quantisation step of the reference binary encoder (not used by ``.fap`` text
    files, which carry the unquantised integer values).
    """

    number: int
    name: str
    unit: str
    bidirectional: bool
    direction: str
    feature_point: str
    quant_step: int


_CSV = """\
1,viseme,na,na,na,na,1
2,expression,na,na,na,na,1
3,open_jaw,MNS,U,down,2.1,4
4,lower_t_midlip,MNS,B,down,2.2,2
5,raise_b_midlip,MNS,B,up,2.3,2
6,stretch_l_cornerlip,MW,B,left,2.4,2
7,stretch_r_cornerlip,MW,B,right,2.5,2
8,lower_t_lip_lm,MNS,B,down,2.6,2
9,lower_t_lip_rm,MNS,B,down,2.7,2
10,raise_b_lip_lm,MNS,B,up,2.8,2
11,raise_b_lip_rm,MNS,B,up,2.9,2
12,raise_l_cornerlip,MNS,B,up,2.4,2
13,raise_r_cornerlip,MNS,B,up,2.5,2
14,thrust_jaw,MNS,U,forward,2.1,1
15,shift_jaw,MW,B,right,2.1,1
16,push_b_lip,MNS,B,forward,2.3,1
17,push_t_lip,MNS,B,forward,2.2,1
18,depress_chin,MNS,B,up,2.10,1
19,close_t_l_eyelid,IRISD,B,down,3.1,1
20,close_t_r_eyelid,IRISD,B,down,3.2,1
21,close_b_l_eyelid,IRISD,B,up,3.3,1
22,close_b_r_eyelid,IRISD,B,up,3.4,1
23,yaw_l_eyeball,AU,B,left,3.5,128
24,yaw_r_eyeball,AU,B,left,3.6,128
25,pitch_l_eyeball,AU,B,down,3.5,128
26,pitch_r_eyeball,AU,B,down,3.6,128
27,thrust_l_eyeball,ES,B,forward,3.5,1
28,thrust_r_eyeball,ES,B,forward,3.6,1
29,dilate_l_pupil,IRISD,B,growing,3.5,1
30,dilate_r_pupil,IRISD,B,growing,3.6,1
31,raise_l_i_eyebrow,ENS,B,up,4.1,2
32,raise_r_i_eyebrow,ENS,B,up,4.2,2
33,raise_l_m_eyebrow,ENS,B,up,4.3,2
34,raise_r_m_eyebrow,ENS,B,up,4.4,2
35,raise_l_o_eyebrow,ENS,B,up,4.5,2
36,raise_r_o_eyebrow,ENS,B,up,4.6,2
37,squeeze_l_eyebrow,ES,B,right,4.1,1
38,squeeze_r_eyebrow,ES,B,left,4.2,1
39,puff_l_cheek,ES,B,left,5.1,2
40,puff_r_cheek,ES,B,right,5.2,2
41,lift_l_cheek,ENS,U,up,5.3,2
42,lift_r_cheek,ENS,U,up,5.4,2
43,shift_tongue_tip,MW,B,right,6.1,1
44,raise_tongue_tip,MNS,B,up,6.1,1
45,thrust_tongue_tip,MW,B,forward,6.1,1
46,raise_tongue,MNS,B,up,6.2,1
47,tongue_roll,AU,U,concave upward,6.3/6.4,512
48,head_pitch,AU,B,down,7.1,170
49,head_yaw,AU,B,left,7.1,170
50,head_roll,AU,B,right,7.1,170
51,lower_t_midlip_o,MNS,B,down,8.1,2
52,raise_b_midlip_o,MNS,B,up,8.2,2
53,stretch_l_cornerlip_o,MW,B,left,8.3,2
54,stretch_r_cornerlip_o,MW,B,right,8.4,2
55,lower_t_lip_lm_o,MNS,B,down,8.5,2
56,lower_t_lip_rm_o,MNS,B,down,8.6,2
57,raise_b_lip_lm_o,MNS,B,up,8.7,2
58,raise_b_lip_rm_o,MNS,B,up,8.8,2
59,raise_l_cornerlip_o,MNS,B,up,8.3,2
60,raise_r_cornerlip_o,MNS,B,up,8.4,2
61,stretch_l_nose,ENS,B,left,9.1,1
62,stretch_r_nose,ENS,B,right,9.2,1
63,raise_nose,ENS,B,up,9.3,1
64,bend_nose,ENS,B,right,9.3,1
65,raise_l_ear,ENS,B,up,10.1,1
66,raise_r_ear,ENS,B,up,10.2,1
67,pull_l_ear,ENS,B,left,10.3,1
68,pull_r_ear,ENS,B,right,10.4,1
"""


def _parse(text: str) -> tuple[FapSpec, ...]:
    specs = []
    for line in text.strip().splitlines():
        num, name, unit, bi, direction, fp, q = line.split(",")
        specs.append(FapSpec(int(num), name, unit, bi == "B", direction, fp, int(q)))
    assert [s.number for s in specs] == list(range(1, N_FAPS + 1))
    return tuple(specs)


FAP_TABLE: tuple[FapSpec, ...] = _parse(_CSV)
"""All 68 FAPs; ``FAP_TABLE[n - 1]`` is FAP ``n``."""

FAP_BY_NAME: dict[str, FapSpec] = {s.name: s for s in FAP_TABLE}
"""FAP specification by name (``"open_jaw"`` -> FAP 3)."""
