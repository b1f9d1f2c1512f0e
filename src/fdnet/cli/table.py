"""`fdnet table`: results of several ``fdnet evaluate --json`` files (and ``fdnet reproduce``'s
``comparison.json``) as one methods x datasets table for a paper or a sheet
(:func:`fdnet.evaluation.tables.table_command`)."""

from __future__ import annotations


def register(sub) -> None:
    from fdnet.evaluation.tables import DEFAULT_METRICS, FORMATS, METRICS

    p = sub.add_parser(
        "table",
        help="merge results JSONs into one methods x datasets table (latex, markdown, csv), best marked",
        description="Merge the results of several `fdnet evaluate --json` files (and `fdnet reproduce`'s "
        "comparison.json) into one table: a row per method, a column per dataset and metric, the "
        "best value of each column marked (bold; a trailing * in csv).",
    )
    p.add_argument(
        "results",
        nargs="+",
        metavar="[LABEL=]RESULTS.json",
        help="results files; LABEL= names the dataset of every result in the file (default: the "
        "result's own data description)",
    )
    p.add_argument("--format", choices=FORMATS, default="markdown", help="table style (default markdown)")
    p.add_argument(
        "--metrics",
        default=",".join(DEFAULT_METRICS),
        metavar="M[,M...]",
        help=f"columns per dataset, from {', '.join(METRICS)} (default {','.join(DEFAULT_METRICS)})",
    )
    p.add_argument(
        "--accept",
        metavar="RULE",
        help="the acceptance rule whose PR numbers (R@100P, AUC-PR, ...) are shown (the results must hold "
        "it: evaluate --accept raw,RULE); default: each result's first rule, raw unless evaluate was "
        "told otherwise",
    )
    p.add_argument("--digits", type=int, default=3, help="decimals shown (default 3)")
    p.add_argument("--out", metavar="FILE", help="also write the table to FILE")
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.evaluation.tables import table_command

    print(
        table_command(
            args.results,
            style=args.format,
            metrics=args.metrics,
            acceptance=args.accept,
            out=args.out,
            digits=args.digits,
        )
    )
    return 0
