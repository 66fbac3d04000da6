"""What the CSV forms of the data (`HelixData`, `TweezerData`) share: the columns helixrod
does not know, ignored with a warning or an error when reading strictly, and the error
about particular data points that a reader turns into file lines (`PointError`)."""

from __future__ import annotations

import csv
import io
import warnings


class PointError(ValueError):
    """A `ValueError` about particular data points; `points` (indices from 0) lets
    `from_csv` name the file lines instead."""

    def __init__(self, message: str, points):
        super().__init__(message)
        self.points = [int(p) for p in points]


def drop_unknown_columns(path, rows: list[tuple[int, str]], allowed, *, strict: bool) -> list[tuple[int, str]]:
    """`rows` -- `(file line, text)` of the header and every later line -- without the
    header's columns that are not in `allowed`.  With `strict`, such a column is a
    `ValueError` naming it; otherwise a `UserWarning` says which columns are ignored.  A
    row with a number of cells other than the header's is a `ValueError` naming its line."""
    header_line, header = rows[0]
    names = [c.strip() for c in next(csv.reader([header]))]
    unknown = [c for c in names if c not in allowed]
    if not unknown:
        return rows
    if strict:
        raise ValueError(f"{path}:{header_line}: unknown columns {unknown}; allowed: {list(allowed)}")
    warnings.warn(f"{path}:{header_line}: ignoring columns {unknown} (not among {list(allowed)})", UserWarning, stacklevel=3)
    keep = [i for i, c in enumerate(names) if c in allowed]
    out = []
    for lineno, text in rows:
        cells = next(csv.reader([text]))
        if len(cells) != len(names):
            raise ValueError(f"{path}:{lineno}: {len(cells)} cells, expected {len(names)} ({', '.join(names)})")
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="").writerow([cells[i] for i in keep])
        out.append((lineno, buffer.getvalue()))
    return out
