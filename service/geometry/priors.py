"""Anthropometric priors on the ankle-centre-to-shoulder-centre segment."""

# Ankle-centre to shoulder-centre height of an average adult (metres): shoulder
# (acromion) height ~0.82 x stature minus ankle height ~0.07 m, for a mixed adult
# population of mean stature ~1.69 m. The paper's simulations use 1.7.
DEFAULT_HEIGHT_M = 1.32
# Spread of that height across adults (metres): the prior's std in the refinement,
# and the uncertainty of people placed from their shoulders.
DEFAULT_HEIGHT_STD_M = 0.08
# Height of the ankle keypoint (the lateral malleolus) above the sole: ~0.04 x stature, 0.07 m for the same
# population. The pose model's ankle centre stands this far above the ground, so the plane the people fit
# lies this far above the ground and the camera's height above the ground is rho plus this.
DEFAULT_ANKLE_HEIGHT_M = 0.07
