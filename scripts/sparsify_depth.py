#!/usr/bin/env python3
# Benchmark helper (docs/BENCHMARKS.md, "The room, a fourth look"): usage sparsify_depth.py SRC DST.
# Copies a generated scene, keeping depth at 1 pixel in 32 ((x*7 + y*13) % 32 == 0) in the
# training frames (every 8th frame, from 0, stays whole: the test split).
import json, os, shutil, struct, sys, zlib
src, dst = sys.argv[1], sys.argv[2]
shutil.rmtree(dst, ignore_errors=True); shutil.copytree(src, dst)
def read16(p):
    d=open(p,'rb').read(); i=8; idat=b''
    while i<len(d):
        n=struct.unpack('>I',d[i:i+4])[0]; t=d[i+4:i+8]; c=d[i+8:i+8+n]; i+=12+n
        if t==b'IHDR': w,h,bd,ct=struct.unpack('>IIBB',c[:10])
        if t==b'IDAT': idat+=c
    assert bd==16 and ct==0
    raw=zlib.decompress(idat); bpp=2; stride=w*bpp; out=[]; prev=bytearray(stride); pos=0
    for y in range(h):
        ft=raw[pos]; pos+=1; line=bytearray(raw[pos:pos+stride]); pos+=stride
        for x in range(stride):
            a=line[x-bpp] if x>=bpp else 0; b=prev[x]; c=prev[x-bpp] if x>=bpp else 0
            if ft==1: line[x]=(line[x]+a)&255
            elif ft==2: line[x]=(line[x]+b)&255
            elif ft==3: line[x]=(line[x]+(a+b)//2)&255
            elif ft==4:
                p_=a+b-c; pa=abs(p_-a); pb=abs(p_-b); pc=abs(p_-c)
                line[x]=(line[x]+(a if pa<=pb and pa<=pc else b if pb<=pc else c))&255
        out.append([struct.unpack('>H',line[2*k:2*k+2])[0] for k in range(w)]); prev=line
    return w,h,out
def write16(p,w,h,rows):
    raw=b''.join(b'\0'+b''.join(struct.pack('>H',v) for v in r) for r in rows)
    chunk=lambda t,c: struct.pack('>I',len(c))+t+c+struct.pack('>I',zlib.crc32(t+c)&0xffffffff)
    open(p,'wb').write(b'\x89PNG\r\n\x1a\n'+chunk(b'IHDR',struct.pack('>IIBBBBB',w,h,16,0,0,0,0))+chunk(b'IDAT',zlib.compress(raw))+chunk(b'IEND',b''))
t=json.load(open(os.path.join(dst,'transforms.json')))
kept=0
for i,f in enumerate(t['frames']):
    if i%8==0: continue
    p=os.path.join(dst,f['depth_file_path']); w,h,rows=read16(p)
    rows=[[v if (x*7+y*13)%32==0 else 0 for x,v in enumerate(r)] for y,r in enumerate(rows)]
    kept+=sum(1 for r in rows for v in r if v); write16(p,w,h,rows)
print(dst, 'kept', kept, 'depth pixels in training frames')
