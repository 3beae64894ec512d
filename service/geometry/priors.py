"""Anthropometric priors on the ankle-centre-to-shoulder-centre segment."""

# Ankle-centre to shoulder-centre height of an average adult (metres): shoulder
# (acromion) height ~0.82 x stature minus ankle height ~0.07 m, for a mixed adult
# population of mean stature ~1.69 m. The paper's simulations use 1.7.
DEFAULT_HEIGHT_M = 1.32
# Spread of that height across adults (metres): the prior's std in the refinement,
# and the uncertainty of people placed from their shoulders.
DEFAULT_HEIGHT_STD_M = 0.08
