"""Analysis of a scenario before it runs: sampled-data stability of the loop linearised at consensus."""
