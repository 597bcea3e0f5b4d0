"""Analysis of a scenario before it runs: sampled-data stability of the loop linearised at consensus."""

# `check` computes the delay margin up to this many agents unless --delay-agents says otherwise.
# The delayed loop does not decouple by graph modes (agent i weighs its own fresh state by its
# degree and its neighbours' delayed ones by the adjacency, and D and Adj do not commute), so
# its augmented state has 12N + M + d(6N + M) entries. On 2 cores, with the search started from
# `crossing_delay`'s guess and the radii above 2000 states from two shift-invert searches,
# `check` takes 2.6 s on hil_6uav, 1.5–3.5 s on random trees of 12–32 agents, 6.9 s at 50, 11 s
# at 64 and 32 s at 100 agents (the guess's dense eigenproblems of T, (3N)³ each, dominate there).
# Kept here, not in `stability_report`, so that the command line can show it without importing
# scipy.
DELAY_MAX_AGENTS = 50
