"""Write the paper's printed Table 1 in the authors' per-class results format, to run the Table-1
pipeline on published numbers:

    python experiments/paper_table1_csv.py outputs/paper_table1_results.csv
    python -m pairedgta +experiment=paper_table stages=[plot] plot.table_csv=outputs/paper_table1_results.csv
    python -m pairedgta +experiment=paper_table stages=[plot] plot.table_csv=outputs/paper_table1_results.csv metric=strict

Absences are inferred from the print (see printed_table_as_results); the authors' released CSV has the
real pixel masses and gives the exact strict numbers."""
from __future__ import annotations

import sys

from pairedgta.figures.paper_table import printed_table_as_results

if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python experiments/paper_table1_csv.py OUT.csv")
    print(printed_table_as_results(sys.argv[1]))
