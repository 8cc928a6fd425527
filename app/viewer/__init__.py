"""The desktop viewer (`kgs-app view`): imgui-bundle for the controls, moderngl for the splats.

`source.py` gets splat sets from a run directory (in process) or a running `kgs-app serve`;
`state.py` holds what the user chose; `gl_renderer.py` draws splats with any moderngl context
(a window's, or a headless EGL one for tests and screenshots); `controls.py` is the imgui panel;
`window.py` puts them in a window.
"""
