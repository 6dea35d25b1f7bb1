# Sourced by .ci/run: the real CloudCompare 2.13 + PythonRuntime for the tests marked
# `cloudcompare`, when ../shared/cloudcompare-python/ is present (the tests skip, saying so,
# when it is absent). Unpacks it into /opt/cloudcompare-python, installs its runtime libraries,
# Xvfb and PySide2 (the GUI test harness drives the menu with it), and gives CloudCompare's
# Python 3.11 the project's packages: the project venv itself when it is Python 3.11, else a
# Python 3.11 venv in /opt/ccpy (exported as TUNNELDEF_CC_SITE).
CC_SHARED=../shared/cloudcompare-python
CC_TARBALL=$CC_SHARED/cloudcompare-2.13.1-pythonruntime-qt5-debian12.tar.gz
if [ -f "$CC_TARBALL" ]; then
    apt-get install -y libqt5widgets5 libqt5opengl5 libqt5concurrent5 libqt5printsupport5 \
        libqt5svg5 libpython3.11 python3.11-venv libgl1 libgomp1 xvfb xauth \
        python3-pyside2.qtwidgets python3-pyside2.qtcore python3-pyside2.qtgui
    if [ ! -x /opt/cloudcompare-python/bin/CloudCompare ]; then
        tar xzf "$CC_TARBALL" -C /opt
    fi
    if ! python -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
        /usr/bin/python3.11 -m venv /opt/ccpy && /opt/ccpy/bin/pip install -q .
        export TUNNELDEF_CC_SITE=/opt/ccpy/lib/python3.11/site-packages
    fi
    export TUNNELDEF_CC_PREFIX=/opt/cloudcompare-python
    # a few crash-free runs of the plugin's three jobs in the real runtime (50 in the benchmark)
    python benchmarks/plugin_runtime.py crashes --runs 5 --max-crashes 0
else
    echo "no $CC_SHARED: the tests in the real CloudCompare will be skipped"
fi
