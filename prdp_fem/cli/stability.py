"""``prdp-fem stability``: the stiff and extreme-case suite."""

from __future__ import annotations

import time

from ._shared import progress


def stability_command(args) -> int:
    from .._atomic import write_text_atomic
    from ..studies.stability import format_markdown, run_case, suite_passed, write_csv
    from ..studies.stability_cases import CASES, case_named

    cases = [case_named(name) for name in args.case] if args.case else \
        [c for c in CASES if c.fast or not args.fast]
    args.out.mkdir(parents=True, exist_ok=True)
    markdown, table = args.out / "stability.md", args.out / "stability.csv"
    results, start = [], time.perf_counter()
    with progress(len(cases), "cases") as bar:
        for case in cases:
            bar.set_postfix_str(case.name)
            results.append(run_case(case))
            write_csv(results, table)  # after every case: an interrupted run keeps its rows
            write_text_atomic(markdown, format_markdown(results))
            bar.update()
    print(format_markdown(results), end="")
    passed = suite_passed(results)
    failed = [r.case for r in results if r.verdict == "FAIL" or r.nonfinite]
    print(f"{len(results)} cases: {sum(r.verdict == 'ok' for r in results)} ok, "
          f"{sum(r.verdict == 'flagged' for r in results)} flagged, {len(failed)} failed"
          + (f" ({', '.join(failed)})" if failed else "")
          + f" in {time.perf_counter() - start:.0f} s; tables in {markdown}, {table}")
    return 0 if passed else 1
