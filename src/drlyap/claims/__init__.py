"""What a certificate claims: one module per kind of claim (its parts, its sentence, how the checker re-proves it),
the words they are made of (:mod:`drlyap.wording`) and the registry that gathers the kinds
(:mod:`drlyap.claims.registry`)."""
