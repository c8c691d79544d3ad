"""`signerf view`: the trained NeRF, its cameras and the edit's selection in a browser (viser), with
the edit's preview and settings one click away. A thin layer: it renders, places, previews and
saves through the same functions as the command line (`nerf.render`, `editing.place`,
`editing.commands`)."""
