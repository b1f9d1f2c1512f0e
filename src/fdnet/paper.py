"""The paper's own numbers (Qin et al.), transcribed from its Tables 3, 4 and 5, shown beside ours.

Tables 3 and 4 give, per dataset pair, recall at 100 % precision and precision at maximum recall
(as fractions here; the paper prints percentages). The paper names a pair ("summer-winter") but
not which condition is the query, so its numbers are shown for both directions of the pair.
Tables 2 (FDNet per vector length) and 5 (every method: extraction ms/image on an NVIDIA TITAN X,
matching ms/query on an Intel Xeon at 2.10 GHz) are :data:`PAPER_TABLE2` and :data:`PAPER_TABLE5`
(``fdnet benchmark`` quotes them too).
"""

from __future__ import annotations

import re

#: the paper's row name -> our method name (``fdnet methods``)
PAPER_METHODS = {
    "FDNet_512": "fdnet",
    "Conv3": "conv3",
    "Gist": "gist",
    "DBow3": "dbow",
    "Landmarks": "landmarks",
    "Conv4_fine-tuned": "hybridnet",
    "NetVLAD": "netvlad",
    "CALC": "calc",
}

#: Qin et al., Table 2 (TITAN X): FDNet_L extraction ms/image and matching ms/query on Nordland.
PAPER_TABLE2 = {256: (20.9, 0.32), 512: (21.2, 0.35), 1024: (22.6, 0.36), 2048: (28.7, 0.40)}
#: Qin et al., Table 5 (Nordland, 2000 images; extraction on a TITAN X, matching on a Xeon at
#: 2.1 GHz): method -> (extraction ms/image, matching ms/query). Keys are fdnet's method names
#: where fdnet has the method (Conv4 fine-tuned is HybridNet's conv4, DBoW3 is dbow).
PAPER_TABLE5 = {
    "conv3": (136.0, 0.34),
    "gist": (223.0, 0.38),
    "dbow": (2.3, 0.013),
    "landmarks": (737.0, 19.0),
    "hybridnet": (158.0, 0.36),
    "netvlad": (980.0, 0.038),
    "calc": (39.0, 0.31),
    "fdnet": (21.2, 0.35),
}

_TABLE3_PAIRS = ("spring-summer", "spring-fall", "spring-winter", "summer-fall", "summer-winter", "fall-winter")
# Table 3 (Nordland), per method: (R@100P %, P@maxR %) for each pair in _TABLE3_PAIRS order
_TABLE3 = {
    "FDNet_512": ((51.83, 16.42), (52.69, 24.83), (40.52, 3.50), (88.52, 93.20), (33.74, 3.82), (33.39, 5.40)),
    "Conv3": ((1.91, 7.24), (1.47, 9.28), (3.48, 4.89), (1.91, 24.50), (0.35, 3.44), (1.39, 4.22)),
    "Gist": ((14.61, 47.08), (4.87, 51.47), (1.04, 2.27), (63.65, 95.67), (0.35, 2.14), (1.22, 2.28)),
    "DBow3": ((0.52, 1.11), (0.52, 1.19), (0.17, 0.91), (12.0, 3.99), (0.70, 0.84), (0.52, 0.76)),
    "Landmarks": ((7.39, 17.43), (10.43, 17.57), (9.13, 7.49), (80.43, 85.82), (4.78, 4.28), (0.87, 4.03)),
    "Conv4_fine-tuned": ((8.34, 14.6), (2.43, 27.11), (7.34, 8.17), (8.52, 31.88), (1.04, 3.72), (1.04, 4.70)),
    "NetVLAD": ((33.91, 59.43), (37.83, 52.87), (25.22, 22.63), (83.04, 91.63), (30.87, 22.12), (10.00, 21.39)),
    "CALC": ((16.33, 45.41), (41.8, 40.95), (28.92, 15.62), (57.90, 85.47), (15.27, 20.13), (15.10, 15.58)),
}

# Table 4: (dataset, the paper's pair name, the condition names fdnet's adapter gives that pair)
_TABLE4_PAIRS = (
    ("alderley", "day-night", ("day", "night")),
    ("oxford_robotcar", "night-day", ("2014-12-10-18-10-50", "2014-12-16-09-14-09")),
    ("st_lucia", "morning-afternoon", ("190809_0845", "180809_1545")),
    ("fas", "summer-winter", ("localization-2", "mapping")),
)
_TABLE4 = {
    "FDNet_512": ((10.82, 10.28), (7.13, 9.73), (14.43, 11.13), (24.80, 15.69)),
    "Conv3": ((0.37, 9.41), (2.57, 12.22), (0.17, 9.06), (3.80, 10.11)),
    "Gist": ((2.24, 20.15), (5.40, 11.85), (2.43, 8.42), (4.77, 7.99)),
    "DBow3": ((1.12, 3.85), (1.74, 7.00), (0.87, 5.37), (0.42, 2.96)),
    "Landmarks": ((1.12, 22.75), (2.77, 16.60), (3.91, 20.54), (1.42, 14.41)),
    "Conv4_fine-tuned": ((4.48, 6.10), (7.73, 10.91), (5.40, 12.31), (8.28, 12.26)),
    "NetVLAD": ((11.54, 33.40), (8.97, 31.27), (13.04, 24.23), (20.11, 22.35)),
    "CALC": ((6.40, 19.30), (6.97, 20.30), (4.83, 16.97), (10.46, 15.69)),
}

PAPER_HARDWARE = (
    "feature extraction on an NVIDIA TITAN X (12 GB), matching on an Intel Xeon CPU at 2.10 GHz, "
    "averaged over 2000 Nordland images (paper section 5.4)"
)


def _norm(name: str) -> str:
    return re.sub(r"[-_ ]", "", name.lower())


def dataset_key(dataset_format: str | None, root_name: str) -> str | None:
    """Which of the paper's datasets this is: the adapter's name, else a folder name that says
    Nordland (the paper's Table 3 conditions are Nordland's seasons); None when not one of them."""
    if dataset_format and dataset_format not in ("folders", "auto"):
        return dataset_format
    return "nordland" if "nordland" in root_name.lower() else None


def paper_pair(dataset: str | None, reference: str, query: str) -> tuple[str, dict[str, dict[str, float]]] | None:
    """(source, {our method: {"recall_at_100_precision", "precision_at_max_recall"}}) of the
    paper's table for this pair of conditions, in either direction; None when the paper has none."""
    if dataset is None:
        return None
    pair = {_norm(reference), _norm(query)}
    if dataset == "nordland":
        for column, name in enumerate(_TABLE3_PAIRS):
            if {_norm(c) for c in name.split("-")} == pair:
                return f"paper Table 3, Nordland {name}", _numbers(_TABLE3, column)
    for column, (table_dataset, name, conditions) in enumerate(_TABLE4_PAIRS):
        if table_dataset == dataset and {_norm(c) for c in conditions} == pair:
            return f"paper Table 4, {dataset} {name}", _numbers(_TABLE4, column)
    return None


def _numbers(table: dict, column: int) -> dict[str, dict[str, float]]:
    return {
        PAPER_METHODS[row]: {
            "paper_name": row,
            "recall_at_100_precision": round(values[column][0] / 100.0, 6),
            "precision_at_max_recall": round(values[column][1] / 100.0, 6),
        }
        for row, values in table.items()
    }


def paper_runtime(method: str) -> dict | None:
    """The paper's Table 5 row (:data:`PAPER_TABLE5`) for our method name, or None."""
    if method not in PAPER_TABLE5:
        return None
    extraction, matching = PAPER_TABLE5[method]
    row = next(row for row, ours in PAPER_METHODS.items() if ours == method)
    return {"paper_name": row, "ms_per_image": extraction, "ms_per_query": matching}
