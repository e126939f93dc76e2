"""Reports of results (`results/*.md` + `.json`): one way to format, judge and stamp numbers
(`pipeline.reporting.common`), and the reports built on it."""
