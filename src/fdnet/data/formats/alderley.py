"""Alderley day/night (Milford and Wyeth, "SeqSLAM: Visual route-based navigation for sunny summer
days and stormy winter nights", ICRA 2012; QUT, https://wiki.qut.edu.au/pages/viewpage.action?pageId=181178395).

The release holds frames extracted from two drives of one route around Alderley, Brisbane, and
"manually ground-truthed frame correspondences" (QUT dataset page). Expected folder as it
unpacks::

    alderley/FRAMESA/Image00001.jpg ...   rainy night
    alderley/FRAMESB/Image00001.jpg ...   sunny day
    alderley/<correspondence file>        rows: FRAMESA frame number, FRAMESB frame number

Protocol (Qin et al. 5.2.1, Table 1): tolerance 2 frames; the first 1000 frames are the test set
and the rest train the network. ``test`` = the first 1000 query frames; the reference map is the
stretch of the other drive they correspond to. Default pair: night queries against the day map.

Not confirmed from public sources here (make them settings, not guesses):
* the correspondence file's name: looked up as ``framematches.csv``, ``fm.csv``, ``ground_truth.csv``
  or any ``*match*.csv|txt``; ``correspondences=FILE`` names it;
* its column order: assumed FRAMESA then FRAMESB (``first_column``/``second_column`` swap them);
* that FRAMESA is the night drive and FRAMESB the day drive (the condition names ``night``/``day``
  are aliases of those folders; ``--reference FRAMESA`` works too);
* that the numbers in the file are the numbers in the image names (``numbering=positions`` or
  ``positions1`` reads them as 0- or 1-based positions; a file of image names also works).
"""

from __future__ import annotations

from dataclasses import dataclass

from fdnet.data.formats._common import fixed
from fdnet.data.formats._paired import PairedFormat

TEST_FRAMES = 1000


@dataclass
class AlderleyOptions:
    tolerance: int = 2  # frames (Table 1)
    correspondences: str | None = None  # file (relative to the dataset folder or absolute)
    first_column: int = 0  # column of FRAMESA (night) frame numbers
    second_column: int = 1  # column of FRAMESB (day) frame numbers
    numbering: str = "names"  # the file's numbers are: names (numbers in image names), positions (0-based), positions1


class AlderleyFormat(PairedFormat):
    name = "alderley"
    summary = "Alderley day/night: FRAMESA (night), FRAMESB (day) and the frame-correspondence file"
    Options = AlderleyOptions
    conditions = {"night": ("FRAMESA",), "day": ("FRAMESB",)}
    first, second = "night", "day"
    default_reference, default_query = "day", "night"
    correspondence_names = (
        "framematches.csv",
        "frame_matches.csv",
        "fm.csv",
        "ground_truth.csv",
        "groundtruth.csv",
        "framematches.txt",
    )
    correspondence_globs = ("*match*.csv", "*match*.txt", "*.csv")
    split_rules = {"test": fixed(0, TEST_FRAMES), "train": fixed(TEST_FRAMES, None)}
    splits = {
        "test": f"first {TEST_FRAMES} query frames and the reference stretch they match",
        "train": "every frame outside the test stretch, in both drives",
    }
    default_eval_split = "test"
    default_train_split = "train"


FORMAT = AlderleyFormat()
