"""facecast: real-time example-based facial expression cloning over the network.

The work lives in the subpackages protocol, rig, server and client; this top-level
package only names the version.
"""

__version__ = "0.1.0"
