"""Pictures of what a camera sees (issue 4): pure functions from results to images, and PNG bytes.

- `ground`: the ground frame (the stored `ground_m`), ground <-> camera <-> pixels, the visible ground;
- `grid`: ground grid lines clipped to the visible ground;
- `overlay`: the frame with grid, people boxes and nearest-neighbour distances (Fig. 1 of Fei et al.);
- `topdown`: a map of the people from above;
- `heatmap`: where and when violations happened;
- `png`: PNG encoding;
- `style`: sizes, colours and labels shared by the renderers.
"""
