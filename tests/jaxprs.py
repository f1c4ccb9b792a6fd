"""Walking a jaxpr: the equations of one primitive, inside scans, conds and custom rules too."""


def equations(jaxpr, primitive: str) -> list:
    """Every equation of `primitive` (its name, e.g. "conv_general_dilated") in `jaxpr` and its
    sub-jaxprs (a ClosedJaxpr's Jaxpr, or a Jaxpr, held in an equation's parameters)."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == primitive:
            found.append(eqn)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found += equations(inner, primitive)
    return found
