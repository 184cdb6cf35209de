"""Registers the bimacppo Gymnasium ids the moment ``gymnasium`` is imported.

Gymnasium 1.x has no entry-point plugin system: ``gym.make("bimacppo/...")`` only finds ids that
some imported code registered. This module closes that gap without importing anything heavy:
``install()`` puts a one-shot finder on ``sys.meta_path`` that lets the normal finders locate
``gymnasium`` and, once gymnasium's own ``__init__`` has run, calls
``bimacppo_learning.register_envs()`` (string entry points only; the env module is imported by
``gym.make`` itself). If gymnasium is already imported, ``install()`` registers at once.

It must stay standalone (standard library only, no package-relative import): the install writes
this source into a ``.pth`` file that every interpreter of the environment executes at start-up,
and that must not import ``bimacppo_learning`` (the deployed planner's processes must not load the
training stack unless they import gymnasium). setup.py builds that ``.pth`` from this file.
"""
import sys

_HOOK_NAME = "bimacppo_learning gymnasium ids"


def _register():
    try:
        import bimacppo_learning
        bimacppo_learning.register_envs()
    except Exception as exc:  # never break the user's `import gymnasium`
        import warnings
        warnings.warn(f"bimacppo_learning: could not register its Gymnasium ids: "
                      f"{type(exc).__name__}: {exc}", RuntimeWarning, stacklevel=2)


class GymnasiumImportHook:
    """A ``sys.meta_path`` finder that only watches for ``gymnasium`` and then removes itself."""

    name = _HOOK_NAME

    @classmethod
    def find_spec(cls, fullname, path=None, target=None):
        if fullname != "gymnasium":
            return None
        _uninstall()
        spec = None
        for finder in list(sys.meta_path):
            find = getattr(finder, "find_spec", None)
            if find is not None:
                spec = find(fullname, path, target)
                if spec is not None:
                    break
        loader = getattr(spec, "loader", None)
        exec_module = getattr(loader, "exec_module", None)
        if exec_module is None:
            return spec

        def exec_then_register(module):
            try:
                exec_module(module)
            finally:
                try:
                    del loader.exec_module   # back to the loader's own method
                except AttributeError:
                    pass
            _register()

        try:
            loader.exec_module = exec_then_register
        except (AttributeError, TypeError):   # a loader that takes no attributes: no hook
            return spec
        return spec


def _uninstall():
    sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "name", None) != _HOOK_NAME]


def install():
    """Register now if gymnasium is loaded, else once it is (idempotent)."""
    if "gymnasium" in sys.modules:
        _register()
        return
    if not any(getattr(f, "name", None) == _HOOK_NAME for f in sys.meta_path):
        sys.meta_path.insert(0, GymnasiumImportHook)
