"""Freiburg Across Seasons, FAS (Naseer, Spinello, Burgard, Stachniss, "Robust visual robot
localization across seasons using network flows", AAAI 2014; University of Freiburg
AIS datasets).

A car drove a route in Freiburg in summer (the ``Mapping`` sequence) and again in winter
(``Localization-1``, ``Localization-2``...); ground truth gives, for each localization frame, the
corresponding Mapping frame. Expected folder as it unpacks::

    fas/Mapping/<frames>            reference (summer)
    fas/Localization-2/<frames>     query (winter); Localization_2, localization2 also accepted
    fas/<ground-truth file>         rows: Localization-2 frame, Mapping frame

Protocol (Qin et al. 5.2.1, Table 1): Localization-2 against Mapping, tolerance 3 frames; 3130
image pairs for training and 1347 for testing. ``train`` = the first 3130 query frames, ``test``
= the next 1347, each with the Mapping stretch its queries correspond to.

Not confirmed from public sources here (settings, not guesses): the ground-truth file's name
(looked up as ``groundtruth.txt``, ``gt.txt``, ``ground_truth.csv``, ``*Localization*2*``,
``*gt*``; ``correspondences=FILE`` names it), its column order (Localization frame first;
``first_column``/``second_column`` swap), whether it holds frame numbers or file names (both
are read; numbers are matched to the numbers in the image names, or to 0-based positions when the
names carry no distinct number), and which 3130/1347 pairs the paper used (taken here in
traversal order).
"""

from __future__ import annotations

from dataclasses import dataclass

from fdnet.data.formats._common import fixed
from fdnet.data.formats._paired import PairedFormat

TRAIN_PAIRS, TEST_PAIRS = 3130, 1347


@dataclass
class FASOptions:
    tolerance: int = 3  # frames (Table 1)
    correspondences: str | None = None
    first_column: int = 0  # column of the localization (query) frames
    second_column: int = 1  # column of the Mapping frames
    numbering: str = "names"  # the file's numbers are: names (numbers in image names), positions (0-based), positions1


class FASFormat(PairedFormat):
    name = "fas"
    summary = "Freiburg Across Seasons: Mapping and Localization-2 frames with their ground-truth pairs"
    Options = FASOptions
    conditions = {"localization-2": ("Localization-2", "Localization2", "Loc2"), "mapping": ("Mapping",)}
    first, second = "localization-2", "mapping"
    default_reference, default_query = "mapping", "localization-2"
    correspondence_names = (
        "groundtruth.txt",
        "ground_truth.txt",
        "gt.txt",
        "ground_truth.csv",
        "groundtruth.csv",
        "gt.csv",
    )
    correspondence_globs = ("*ocalization*2*.txt", "*ocalization*2*.csv", "*gt*.txt", "*gt*.csv")
    split_rules = {"train": fixed(0, TRAIN_PAIRS), "test": fixed(TRAIN_PAIRS, TRAIN_PAIRS + TEST_PAIRS)}
    splits = {"train": f"first {TRAIN_PAIRS} query frames", "test": f"next {TEST_PAIRS} query frames"}
    default_eval_split = "test"
    default_train_split = "train"


FORMAT = FASFormat()
