"""The committed run records (records/, appendix 09d) against their budget: megabytes per scale,
in all, and per medium run (data, actor and marker; the timing sidecar is a few hundred bytes)."""

from collections import defaultdict

from pemamoe.records import RECORD_BUDGET_MB, RECORDS_DIR, committed_records_mb


def main() -> None:
    sizes = {scale: mb for scale, mb in committed_records_mb().items() if scale != "ci"}
    total = sum(sizes.values())
    print(f"records: {total:.1f} MB committed of a {RECORD_BUDGET_MB['committed']:g} MB budget "
          f"({total / RECORD_BUDGET_MB['committed']:.0%}); "
          + (", ".join(f"{scale} {mb:.1f} MB" for scale, mb in sizes.items()) or "none yet"))
    runs = defaultdict(float)
    for f in (RECORDS_DIR / "medium").glob("*"):
        runs[f.name.split(".")[0]] += f.stat().st_size / 1e6
    if runs:
        print(f"records: medium runs {min(runs.values()):.2f}-{max(runs.values()):.2f} MB each "
              f"(budget {RECORD_BUDGET_MB['per_medium_run']:g} MB), {len(runs)} runs")


if __name__ == "__main__":
    main()
