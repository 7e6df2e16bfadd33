"""The store and the stages' artifacts as model code reads them: a store's windows, normalizer
and processor (`windows`), reflow's couplings and alignment's targets (`couplings`), and the
frozen encoder's features cache (`features`)."""
