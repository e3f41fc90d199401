"""Sparse linear algebra shared by the stages: esmm's supernodal LDLᵀ factorization
(:mod:`.supernodal`), the Newton helpers of the static solvers (:mod:`.newton`: orderings,
SuperLU factors, descent directions), the simulator's factored and constrained solves
(:mod:`.linsolve`) and the limited-memory quasi-Newton update (:mod:`.quasinewton`).

A ground layer: it imports nothing of esmm but the ground modules (errors, blas).
"""
