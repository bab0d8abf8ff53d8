"""Running a solution: the progressive-refinement solver, its ledger, the accuracy plan and
passes, the strategies and shared runs."""
