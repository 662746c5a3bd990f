"""ament_python set-up of art_guidance (also installable with plain pip)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "art_guidance"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["models/*.pt", "models/*.onnx", "models/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config",
         sorted(glob("config/*.yaml") + glob("config/*.xml") + glob("config/*.json"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
    ],
    python_requires=">=3.11",
    install_requires=[
        "numpy>=1.26",
        "scipy>=1.11",
        "pyyaml>=6",
        "clarabel>=0.9",
        "osqp>=1.0",
        # the learned warm start flies the exported models (`.onnx`) on ONNX Runtime: a flight
        # install (`pip install .`) has no torch and no onnx (README "Installing")
        "onnxruntime==1.30.0",
        # the compiled per-step numerics (art_guidance/kernels; numpy is their oracle and the
        # fallback where numba is missing): pinned with the llvmlite it is built against
        "numba==0.68.1",
        "llvmlite==0.50.0",
        # the recorder uses Writer.flush() and the private mcap_ros2._dynamic encoder: bounded
        # to the minor versions tested (.ci/constraints.txt pins mcap 1.6.0, support 0.6.0)
        "mcap>=1.6,<1.7",
        "mcap-ros2-support>=0.6,<0.7",
        "tqdm>=4.66",
        "matplotlib>=3.8",
    ],
    extras_require={
        # train, export, distill, dagger (and the torch runtime of checkpoints); the commands
        # name this extra when it is missing (art_guidance.extras)
        "train": ["torch==2.13.0", "onnx==1.23.1"],
        # pytest-cov 7 and coverage 7.10+ for `make coverage` (coverage's own subprocess patch)
        "test": ["pytest>=8", "pytest-xdist>=3.6", "pytest-cov>=7", "coverage>=7.10",
                 "cvxpy>=1.5", "rosbags>=0.10", "flake8>=7"],
        "distributed": ["ray[default]>=2.9"],
    },
    zip_safe=True,
    maintainer="art_guidance maintainers",
    maintainer_email="art-guidance@example.com",
    description="Onboard rendezvous guidance with a transformer warm start and robust SCP.",
    license="MIT",
    entry_points={
        "console_scripts": [
            f"guidance_node = {PACKAGE}.ros.guidance_node:main",
            f"guidance_managed_node = {PACKAGE}.ros.guidance_node:main_managed",
            f"sim_node = {PACKAGE}.ros.sim_node:main",
            f"art-guidance = {PACKAGE}.cli:main",
        ],
    },
)
