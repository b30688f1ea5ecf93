"""Where numba caches the compiled kernels, chosen before numba is imported.

numba looks for a writable folder next to the package (``__pycache__``), then in the user's
cache folder (``$XDG_CACHE_HOME`` or ``~/.cache``); a user who can write neither (an installed
package, a service account without a home) got ``RuntimeError: cannot cache function ...: no
locator available`` on every run. Then a private folder in the temporary directory is used, and
if none can be made, the kernels are compiled on each run without a cache; `NOTE` says which.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

__all__ = ["configure", "user_cache_base", "CACHE", "NOTE"]

#: Whether the kernels are compiled with ``cache=True`` (`cfm_fem._kernels.JIT`).
CACHE = True
#: What `configure` changed, for the command line to say once; None when numba's own choice
#: works.
NOTE: str | None = None


def _writable(folder: Path) -> bool:
    """True if ``folder`` exists or can be made, and a file can be created in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError:
        return False
    return True


def _private(folder: Path) -> bool:
    """True if ``folder`` is (or is now made) a folder of this user's alone, not a link: one
    in a shared temporary directory that another user made could feed us compiled code."""
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        st = os.lstat(folder)
    except OSError:
        return False
    own = not hasattr(os, "getuid") or st.st_uid == os.getuid()
    return stat.S_ISDIR(st.st_mode) and own and not st.st_mode & 0o022 and _writable(folder)


def user_cache_base(env) -> Path | None:
    """The user's cache folder (``$XDG_CACHE_HOME``, else ``~/.cache``; None without either)."""
    base = env.get("XDG_CACHE_HOME") or (
        os.path.join(env["HOME"], ".cache") if env.get("HOME") else None
    )
    return None if base is None else Path(base)


def _user_cache(env) -> Path | None:
    base = user_cache_base(env)
    return None if base is None else base / "numba"


def configure(package_dir=None, env=None, temp_dir=None) -> str | None:
    """Choose numba's cache folder for the kernels; return a note when it is not numba's own.

    Parameters
    ----------
    package_dir : path-like, optional
        The folder of the kernels' source (default: this package's).
    env : mapping, optional
        The environment (default ``os.environ``); ``NUMBA_CACHE_DIR`` is set in it when a
        fallback folder is chosen.
    temp_dir : path-like, optional
        Where to make the fallback folder (default ``tempfile.gettempdir()``).

    Returns
    -------
    str or None
        What was chosen, or None when the user's ``NUMBA_CACHE_DIR``, the package's
        ``__pycache__`` or the user cache folder is writable.
    """
    global CACHE, NOTE
    env = os.environ if env is None else env
    given = env.get("NUMBA_CACHE_DIR")
    if given and _writable(Path(given)):
        return None
    package = Path(__file__).parent if package_dir is None else Path(package_dir)
    user = _user_cache(env)
    if _writable(package / "__pycache__") or (user is not None and _writable(user)):
        return None  # numba finds one of these itself
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    temp = Path(tempfile.gettempdir() if temp_dir is None else temp_dir)
    fallback = temp / f"cfm_fem-numba-{uid}"
    if _private(fallback):
        env["NUMBA_CACHE_DIR"] = str(fallback)
        if "numba" in sys.modules:  # imported before cfm_fem: tell its config as well
            sys.modules["numba"].config.CACHE_DIR = str(fallback)
        NOTE = f"numba caches the compiled kernels in {fallback} (no writable cache folder)"
    else:
        CACHE = False
        NOTE = "no writable folder for numba's cache: the kernels are compiled on each run"
    return NOTE


configure()  # on import: cfm_fem imports this module before anything imports numba
