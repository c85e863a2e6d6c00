"""Write the parameter and diagnostics tables of every env page from the env's
declarations (``param(doc=...)``, ``diagnostics``), and the listing ``beacon-torch list`` prints of the package's envs
(``beacon_torch/data/envs.txt``, so that the command answers without importing torch):
`.venv/bin/python docs/make_env_tables.py`. The test suite checks that both are
current."""

from pathlib import Path

from beacon_torch.cli import LISTING, listing
from beacon_torch.files import write_text
from beacon_torch.params import markdown
from beacon_torch.registry import ENVS, base_envs
from beacon_torch.training.report import write_block

PAGES = Path(__file__).parent / "envs"
BEGIN = "<!-- parameters: written from the env's declarations by docs/make_env_tables.py -->"
END = "<!-- end of the parameters -->"


def page(env_id: str) -> Path:
    """An env's own page, or for a variant without one, its family's."""
    own = PAGES / f"{env_id.removesuffix('-v0')}.md"
    return own if own.exists() else PAGES / f"{env_id.split('-')[0]}.md"


def paged_envs() -> list[str]:
    """The envs whose tables are written: the benchmark's own, and the variants with a
    page of their own."""
    base = base_envs()
    return base + [e for e in ENVS if e not in base and page(e) != page(ENVS[e].base_id())]


def block(env_id: str) -> str:
    """The generated part of an env's page: its parameters, then its diagnostics."""
    cls = ENVS[env_id]
    rows = [
        "The diagnostics, one number per member: in the TensorDict under `diagnostics` and in the "
        "`info` of the gymnasium, Stable-Baselines3 and PettingZoo adapters, beside `blew_up` (the "
        "step ended the member's episode by a blow-up):",
        "",
        "| diagnostic | meaning |",
        "|---|---|",
        *(f"| `{name}` | {doc} |" for name, doc in cls.physics.diagnostics.items()),
    ]
    return markdown(cls.physics.Params) + "\n\n" + "\n".join(rows)


if __name__ == "__main__":
    for env_id in paged_envs():
        print(write_block(page(env_id), BEGIN, END, block(env_id)))
    print(write_text(LISTING, listing()))
