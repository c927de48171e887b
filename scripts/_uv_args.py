"""Print what gives `uv pip install` what pip's own configuration gives pip (pip.conf files and PIP_* variables,
as `pip config list` shows them): first pip's certificate file (for SSL_CERT_FILE; an empty line if none), then,
one per line, the arguments for its indexes, local wheels and constraints. Without them uv would look only at PyPI,
past the wheels (torch's CPU build) and caps this machine keeps on disk."""

import subprocess
import sys

FLAGS = {"index-url": "--index-url", "extra-index-url": "--extra-index-url", "find-links": "--find-links",
         "constraint": "--constraint", "no-index": "--no-index"}

listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True,
                        check=True).stdout
settings: dict[str, str] = {}
for line in listed.splitlines():
    key, _, value = line.partition("=")
    name = key.rpartition(".")[2]
    # later lines win (pip lists its files from global to user, then PIP_* variables as ":env:")
    settings[name] = value.strip().strip("'\"")
args = [settings.get("cert", "")]
for name, flag in FLAGS.items():
    value = settings.get(name)
    if value is None:
        continue
    if flag == "--no-index":
        if value.lower() in ("1", "true", "yes", "on"):
            args.append(flag)
        continue
    for item in value.split():
        args += [flag, item]
print("\n".join(args))
