"""What every stage shares: job plumbing (jobs.py), the window shapes and the Remark-2 rollout maths (rollout.py)."""
