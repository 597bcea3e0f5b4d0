"""Analysis of a scenario before it runs: sampled-data stability of the loop linearised at consensus."""

# `check` computes the delay margin up to this many agents unless --delay-agents says otherwise.
# The delayed loop does not decouple by graph modes (agent i weighs its own fresh state by its
# degree and its neighbours' delayed ones by the adjacency, and D and Adj do not commute), so
# its augmented state has 12N + M + d(6N + M) entries, and its radius needs dense eigenproblems
# (`delay_margin.DENSE_MAX`: ARPACK misses eigenvalues in this clustered spectrum). On 2 cores,
# with the search started from `crossing_delay`'s guess, `check` takes 7.2 s on a 12-agent,
# 13.8 s on a 16-agent and 30 s on a 20-agent random tree (16 s and 50 s without the guess at 12
# and 16); a little above 20 agents the augmented state passes DENSE_MAX. Kept here, not in
# `stability_report`, so that the command line can show it without importing scipy.
DELAY_MAX_AGENTS = 16
