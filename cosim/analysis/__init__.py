"""Analysis of a scenario before it runs: sampled-data stability of the loop linearised at consensus."""

# `check` computes the delay margin up to this many agents unless --delay-agents says otherwise.
# The delayed loop does not decouple by graph modes (agent i weighs its own fresh state by its
# degree and its neighbours' delayed ones by the adjacency, and D and Adj do not commute). On a
# tree of 16 agents or more the margin comes from counts of the roots outside the unit circle,
# O(N) per frequency (`delay_count`): on 2 cores 0.2–0.8 s at 16–100 agents, 6–10 s at 1000 and
# 79 s at 10,000 (random trees). Below 16, the sweep and the radii: 1.6 s on hil_6uav.
# Kept here, not in `stability_report`, so that the command line can show it without importing
# scipy.
DELAY_MAX_AGENTS = 10000
